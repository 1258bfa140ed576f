# unscatter: learned compensation of cell-induced light scattering in DLP bioprinting
# (Guan et al. 2022, Biofabrication 14(1)). Stages and data contract: README.md.

from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/masks.smk"
include: "workflow/rules/lab.smk"
include: "workflow/rules/registration.smk"
include: "workflow/rules/calibration.smk"
include: "workflow/rules/diagnosis.smk"
include: "workflow/rules/nets.smk"
include: "workflow/rules/compensation.smk"
include: "workflow/rules/benchmark.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/layers.smk"


rule all:
    input:
        all_input,
    default_target: True
    localrule: True
