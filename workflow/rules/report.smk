rule report:
    """One HTML page of the run: every stage's figures and tables, each number with the
    file under results/ it comes from."""
    input:
        registered_prints(),
        calibrated_model(),
        f"{RESULTS}/train/{MODEL}",
        lambda w: list(compensated().values()),
        benchmark_targets(),
    output:
        f"{RESULTS}/report.html",
    log:
        f"{RESULTS}/logs/report.log",
    params:
        results=lambda w, output: os.path.dirname(output[0]),
        benchmark_batches=list(BENCHMARK_BATCH),
        code=code_version("report"),
    localrule: True
    script:
        "../scripts/report.py"
