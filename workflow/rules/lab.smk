rule virtual_lab:
    """Print and image every trial mask on the virtual lab: a batch in the data contract.

    The truth (true poses, noise-free prints) goes beside the batch, never into it:
    no later stage may read it except to score.
    """
    input:
        masks=f"{RESULTS}/trial_masks",
        lab_config=lab_config_file,
    output:
        batch=directory(f"{RESULTS}/lab/{{batch}}"),
        truth=directory(f"{RESULTS}/lab/{{batch}}.truth"),
    log:
        f"{RESULTS}/logs/virtual_lab/{{batch}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/virtual_lab/{{batch}}.tsv"
    wildcard_constraints:
        batch=re.escape(config["lab"]["batch"]),
    params:
        seed=config["lab"]["seed"],
        code=code_version("lab", "io", "masks"),
    threads: 1
    resources:
        mem_mb=2000,
        runtime=30,
    script:
        "../scripts/lab_print.py"


rule virtual_lab_benchmark:
    """Print and image the benchmark's print job on the virtual lab, each mask at the
    exposure job.tsv asks for: one batch, registered like every other, scored, never
    calibrated on."""
    input:
        job=f"{RESULTS}/benchmark/print_job",
        lab_config=lab_config_file,
    output:
        batch=directory(f"{RESULTS}/lab/{LAB_BENCHMARK_BATCH}"),
        truth=directory(f"{RESULTS}/lab/{LAB_BENCHMARK_BATCH}.truth"),
    log:
        f"{RESULTS}/logs/virtual_lab/{LAB_BENCHMARK_BATCH}.log",
    benchmark:
        f"{RESULTS}/benchmarks/virtual_lab/{LAB_BENCHMARK_BATCH}.tsv"
    params:
        seed=config["lab"]["seed"] + 1,
        code=code_version("lab", "io", "masks"),
    threads: 1
    resources:
        mem_mb=2000,
        runtime=30,
    script:
        "../scripts/lab_print.py"
