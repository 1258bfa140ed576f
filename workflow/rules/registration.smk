rule register_prints:
    """Register each microscope image of a batch to its mask and threshold it into a print."""
    input:
        batch=batch_folder,
        files=batch_files,
    output:
        directory(f"{RESULTS}/prints/{{batch}}"),
    log:
        f"{RESULTS}/logs/register_prints/{{batch}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/register_prints/{{batch}}.tsv"
    params:
        mode=config["registration"]["mode"],
        level=config["registration"]["level"],
        min_score=config["registration"]["min_score"],
        # The benchmark's prints go on past a failed print: it is scored as 'no print'.
        skip_failed=lambda w: config["registration"]["skip_failed"] or w.batch in BENCHMARK_BATCH,
        code=code_version("imaging", "io"),
    threads: 2
    resources:
        mem_mb=4000,
        runtime=60,
    script:
        "../scripts/register_prints.py"
