# Multi-layer (3-D) prints, when layers.run is true: 3-D trial prints on the virtual lab
# (or measured batches, layers.batches, with source: batches), their z-stacks registered, the depth parameters calibrated on them (with the 2-D model
# in use), the 3-D designs compensated, and the benchmark's print job printed, registered
# and scored. z-stacks that fail registration QC are skipped (never used) and, in the
# benchmark, scored as failed.

rule trial_masks3d:
    """3-D trial prints: bridges, channels, towers, stairs (one PNG a layer)."""
    output:
        directory(f"{LAYERS}/trial_masks"),
    log:
        f"{RESULTS}/logs/layers/trial_masks.log",
    params:
        n=config["layers"]["count"],
        layers=config["layers"]["layers"],
        size=config["layers"]["size"],
        seed=config["layers"]["seed"],
        code=code_version("calibration3d", "io"),
    localrule: True
    script:
        "../scripts/layers.py"


rule virtual_lab3d:
    """Print the 3-D trial prints (trials) or the 3-D benchmark's print job (benchmark) on
    the virtual lab and image them as confocal z-stacks; the truth beside, never read."""
    input:
        masks=lambda w: f"{LAYERS}/trial_masks" if w.b3 == "trials" else f"{LAYERS}/benchmark/print_job",
        lab_config=lab_config_file,
    output:
        batch=directory(f"{LAYERS}/lab/{{b3}}"),
        truth=directory(f"{LAYERS}/lab/{{b3}}.truth"),
    log:
        f"{RESULTS}/logs/layers/virtual_lab_{{b3}}.log",
    wildcard_constraints:
        b3="trials|benchmark",
    params:
        seed=lambda w: config["lab"]["seed"] + (2 if w.b3 == "trials" else 3),
        code=code_version("lab", "io"),
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    script:
        "../scripts/layers.py"


rule register3d:
    """Register the z-stacks of a multi-layer batch (the virtual lab's, or a measured one)
    to their layer masks: voxel prints."""
    input:
        batch=lambda w: LAYER_BATCHES[w.b3],
        files=layer_batch_files,
    output:
        directory(f"{LAYERS}/prints/{{b3}}"),
    log:
        f"{RESULTS}/logs/layers/register_{{b3}}.log",
    params:
        level=config["registration"]["level"],
        code=code_version("imaging", "io"),
    threads: 2
    resources:
        mem_mb=4000,
        runtime=30,
    script:
        "../scripts/layers.py"


rule calibrate3d:
    """The depth parameters (and layers.free) fitted to the registered 3-D trial prints,
    their spread from a bootstrap over the prints."""
    input:
        prints=expand(f"{LAYERS}/prints/{{b3}}", b3=LAYER_TRIALS),
        model=model_dir(MODEL),
    output:
        directory(f"{LAYERS}/calibration"),
    log:
        f"{RESULTS}/logs/layers/calibrate3d.log",
    params:
        free=config["layers"]["free"],
        bootstrap=config["layers"]["bootstrap"],
        code=code_version("calibration3d", "model", "io", "metrics"),
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
    script:
        "../scripts/layers.py"


rule compensate3d:
    """Layer masks for every 3-D design, optimised together through the calibrated model."""
    input:
        designs=designs3d_files,
        calibration=f"{LAYERS}/calibration",
    output:
        directory(f"{LAYERS}/compensated"),
    log:
        f"{RESULTS}/logs/layers/compensate3d.log",
    params:
        folder=config["layers"]["designs"],
        names=config["layers"]["names"],
        code=code_version("compensation3d", "compensation", "model", "io"),
    threads: 1
    resources:
        mem_mb=6000,
        runtime=60,
    script:
        "../scripts/layers.py"


rule benchmark3d_job:
    """The 3-D benchmark's print job: compensated and identical layer masks per design."""
    input:
        designs=designs3d_files,
        compensated=f"{LAYERS}/compensated",
        calibration=f"{LAYERS}/calibration",
    output:
        directory(f"{LAYERS}/benchmark/print_job"),
    log:
        f"{RESULTS}/logs/layers/benchmark3d_job.log",
    params:
        folder=config["layers"]["designs"],
        code=code_version("compensation3d", "io"),
    localrule: True
    script:
        "../scripts/layers.py"


rule benchmark3d_score:
    """The printed 3-D benchmark scored against the designs: metrics.tsv, sections.png."""
    input:
        prints=expand(f"{LAYERS}/prints/{{b3}}", b3=LAYER_BENCHMARK),
        designs=designs3d_files,
    output:
        directory(f"{LAYERS}/benchmark/scores"),
    log:
        f"{RESULTS}/logs/layers/benchmark3d_score.log",
    params:
        folder=config["layers"]["designs"],
        names=config["layers"]["names"],
        code=code_version("compensation3d", "metrics", "io"),
    localrule: True
    script:
        "../scripts/layers.py"
