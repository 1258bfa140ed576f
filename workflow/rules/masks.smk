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
        criterion=config["trial_masks"]["criterion"],
        fiducials=config["trial_masks"]["fiducials"],
        paper_fiducials=config["trial_masks"]["paper_fiducials"] if config["trial_masks"]["kind"] == "paper" else False,
        code=code_version("masks", "io", *(["design", "model"] if config["trial_masks"]["kind"] == "designed" else [])),
    threads: 2
    resources:
        mem_mb=4000,
        runtime=30,
    script:
        "../scripts/trial_masks.py"


rule next_trial_masks:
    """Sequential design: the masks of the next print batch, chosen where the diagnosis's
    model is least sure, complementing the prints already made (trial_masks.next > 0)."""
    input:
        prints=registered_prints(),
        model=diagnosis_dir(),
    output:
        directory(f"{RESULTS}/next_trial_masks"),
    log:
        f"{RESULTS}/logs/next_trial_masks.log",
    params:
        n=config["trial_masks"]["next"],
        seed=config["trial_masks"]["seed"],
        size=config["trial_masks"]["size"],
        pool=config["trial_masks"]["pool"],
        draws=config["trial_masks"]["draws"],
        criterion=config["trial_masks"]["criterion"],
        fiducials=config["trial_masks"]["fiducials"],
        code=code_version("design", "masks", "prints", "model", "io"),
    threads: 2
    resources:
        mem_mb=4000,
        runtime=30,
    script:
        "../scripts/next_trial_masks.py"
