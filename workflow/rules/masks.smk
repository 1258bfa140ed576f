rule trial_masks:
    """The trial masks: the paper's random checkerboards, rectangles and circles, or
    (trial_masks.kind: designed) masks chosen to teach the printer model the most."""
    output:
        directory(f"{RESULTS}/trial_masks"),
    log:
        f"{RESULTS}/logs/trial_masks.log",
    params:
        n=config["trial_masks"]["count"],
        seed=config["trial_masks"]["seed"],
        size=config["trial_masks"]["size"],
        kind=config["trial_masks"]["kind"],
        pool=config["trial_masks"]["pool"],
        draws=config["trial_masks"]["draws"],
        code=code_version("masks", "io", *(["design", "model"] if config["trial_masks"]["kind"] == "designed" else [])),
    threads: 2
    resources:
        mem_mb=4000,
        runtime=30,
    script:
        "../scripts/trial_masks.py"
