rule report:
    """One HTML page of the run: every stage's figures and tables, each number with the
    file under results/ it comes from."""
    input:
        registered_prints(),
        calibrated_model(),
        diagnosis_dir(),
        f"{RESULTS}/train/{MODEL}",
        lambda w: list(benchmark_masks().values()),
        benchmark_targets(),
        layers_targets(),
    output:
        f"{RESULTS}/report.html",
    log:
        f"{RESULTS}/logs/report.log",
    params:
        results=lambda w, output: os.path.dirname(output[0]),
        benchmark_batches=list(BENCHMARK_BATCH),
        models={"model": config["model"], "other": OTHER},
        code=code_version("report"),
    localrule: True
    script:
        "../scripts/report.py"
