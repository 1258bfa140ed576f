rule augment:
    """Simulated mask/print pairs from the calibrated printer (Guan et al. 2022, 'Data
    augmentation'): the augmentation families, a Zarr store with a train/test split."""
    input:
        model=lambda w: model_dir(w.model),
    output:
        directory(f"{RESULTS}/augment/{{model}}.zarr"),
    log:
        f"{RESULTS}/logs/augment/{{model}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/augment/{{model}}.tsv"
    params:
        pairs=augment_count(),
        seed=config["augmentation"]["seed"],
        size=config["trial_masks"]["size"],
        test_fraction=config["augmentation"]["test_fraction"],
        code=code_version("augment", "masks", "model", "io"),
    threads: 2
    resources:
        mem_mb=4000,
        runtime=30,
    script:
        "../scripts/augment.py"


rule train:
    """The master (design -> mask) and slave (mask -> print) U-Nets of Fig. 4, trained
    with Eq. 2; resumes from its checkpoint when a run was interrupted."""
    input:
        dataset=f"{RESULTS}/augment/{{model}}.zarr",
    output:
        directory(f"{RESULTS}/train/{{model}}"),
    log:
        f"{RESULTS}/logs/train/{{model}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/train/{{model}}.tsv"
    params:
        preset=config["training"]["preset"],
        epochs=config["training"]["epochs"],
        seed=config["training"]["seed"],
        code=code_version("training", "nets", "io", "metrics", "model"),
    threads: 2
    resources:
        mem_mb=8000,
        runtime=600,
        gpu=config["training"]["gpus"],
    script:
        "../scripts/train.py"
