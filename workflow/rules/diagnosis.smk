rule diagnose:
    """The closed loop: held-out residual diagnostics of the calibrated model on the
    prints of every batch, effects of the library added while they lower the held-out
    error beyond the noise, the selected model (model.yaml) and the error before/after."""
    input:
        prints=registered_prints(),
        base=calibrated_model(),
    output:
        directory(diagnosis_dir()),
    log:
        f"{RESULTS}/logs/diagnose.log",
    benchmark:
        f"{RESULTS}/benchmarks/diagnose.tsv"
    params:
        candidates=config["diagnosis"]["candidates"],
        folds=config["diagnosis"]["folds"],
        seed=config["diagnosis"]["seed"],
        quick=config["diagnosis"]["quick"],
        gain_test=config["diagnosis"]["gain_test"],
        code=code_version("diagnosis", "measurement", "fitting", "prints", "model", "io", "metrics"),
    threads: 2  # its fits run in one process a thread, each on one torch thread (unscatter.diagnosis.DEFAULTS workers)
    resources:
        mem_mb=12500,  # the process and its 2 workers: 7,967 and 9,734 MB at most (summed over the processes) in two default runs (results/benchmarks/diagnose.tsv), and each worker 0.4 to 0.7 GB more since it keeps the bands and fold subsets of the shared spectra (docs/diagnosis.md, "What a worker does besides fitting")
        runtime=60,
    script:
        "../scripts/diagnose.py"
