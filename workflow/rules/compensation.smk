rule compensate:
    """Masks for every design by one method: nn (the master network, as the paper), ilt
    (optimised through the calibrated simulator), nn+ilt (the network's mask refined by
    ILT); each also as the full DMD frame."""
    input:
        designs=design_files,
        model=lambda w: model_dir(w.model),
        train=lambda w: [] if w.method == "ilt" else f"{RESULTS}/train/{w.model}",
    output:
        directory(f"{RESULTS}/compensated/{{model}}/{{method}}"),
    log:
        f"{RESULTS}/logs/compensate/{{model}}/{{method}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/compensate/{{model}}/{{method}}.tsv"
    wildcard_constraints:
        method="nn|ilt|nn\+ilt",
    params:
        folder=config["designs"]["folder"],
        names=config["designs"]["names"],
        robust=config["compensation"]["robust"],
        code=code_version("compensation", "nets", "model", "io"),
    threads: 1  # ILT's small FFTs: one thread (unscatter.compensation.ILT_DEFAULTS)
    resources:
        mem_mb=4000,
        runtime=30,
    script:
        "../scripts/compensate.py"
