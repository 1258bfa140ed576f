rule calibrate:
    """Calibrate the printer simulator (Eq. 1) on the registered prints of every batch:
    DEAP genetic algorithm, gradient refinement, k-fold validation, bootstrap spread."""
    input:
        prints=registered_prints(),
    output:
        directory(f"{RESULTS}/calibration/{{model}}"),
    log:
        f"{RESULTS}/logs/calibrate/{{model}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/calibrate/{{model}}.tsv"
    params:
        seed=config["calibration"]["seed"],
        population=config["calibration"]["population"],
        generations=config["calibration"]["generations"],
        folds=config["calibration"]["folds"],
        bootstrap=config["calibration"]["bootstrap"],
        free_c0=config["calibration"]["free_c0"],
        objective=config["calibration"]["objective"],
        code=code_version("calibration", "measurement", "fitting", "prints", "model", "io", "metrics"),
    threads: 2
    resources:
        mem_mb=6000,
        runtime=60,
    script:
        "../scripts/calibrate.py"
