rule benchmark_job:
    """The benchmark's print job: every compensated mask and the identical mask at each
    grey level of benchmark.doses, each at 90, 100 and 110 % exposure (masks/, job.tsv,
    batch.yaml, README.txt). A real printer prints it; with source 'lab' the lab does."""
    input:
        designs=design_files,
        masks=lambda w: list(benchmark_masks().values()),
    output:
        directory(f"{RESULTS}/benchmark/print_job"),
    log:
        f"{RESULTS}/logs/benchmark/print_job.log",
    params:
        methods=list(benchmark_masks()),
        doses=config["benchmark"]["doses"],
        fiducials=config["benchmark"]["fiducials"],
        code=code_version("benchmark", "io", "masks"),
    localrule: True
    script:
        "../scripts/benchmark.py"


rule benchmark_simulated:
    """The benchmark on the calibrated simulator: what the model predicts, before (or
    without) printing; every mask scored as the prints are."""
    input:
        designs=design_files,
        masks=lambda w: list(benchmark_masks().values()),
        model=model_dir(MODEL),
    output:
        directory(f"{RESULTS}/benchmark/simulated"),
    log:
        f"{RESULTS}/logs/benchmark/simulated.log",
    params:
        methods=list(benchmark_masks()),
        doses=config["benchmark"]["doses"],
        code=code_version("benchmark", "metrics", "model", "io"),
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    script:
        "../scripts/benchmark.py"


rule benchmark_score:
    """Score the printed benchmark (registered like every batch) against the designs:
    metrics.tsv (IoU, pixel error, EPE, PV band), summary.tsv and the figures."""
    input:
        designs=design_files,
        prints=lambda w: [f"{RESULTS}/prints/{name}" for name in BENCHMARK_BATCH],
    output:
        metrics=f"{RESULTS}/benchmark/metrics.tsv",
        summary=f"{RESULTS}/benchmark/summary.tsv",
        fig6=f"{RESULTS}/benchmark/fig6_prints.png",
        fig5=f"{RESULTS}/benchmark/fig5_masks.png",
        bars=f"{RESULTS}/benchmark/metrics_bars.png",
    log:
        f"{RESULTS}/logs/benchmark/score.log",
    params:
        code=code_version("benchmark", "metrics", "io", "masks"),
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    script:
        "../scripts/benchmark.py"
