rule trial_masks:
    """The paper's trial masks: checkerboards, rectangles and circles (8-bit PNG)."""
    output:
        directory(f"{RESULTS}/trial_masks"),
    log:
        f"{RESULTS}/logs/trial_masks.log",
    params:
        n=config["trial_masks"]["count"],
        seed=config["trial_masks"]["seed"],
        size=config["trial_masks"]["size"],
        code=code_version("masks", "io"),
    localrule: True
    script:
        "../scripts/trial_masks.py"
