# crashfuse workflow: leave-one-test-out evaluation of the bias-corrected CAE model.
# Thin on purpose: the rules live in workflow/rules/, the settings in config/config.yaml
# (documented in config/README.md, validated against workflow/schemas/config.schema.yaml),
# and every rule calls the crashfuse command line. See docs/workflow.md.

from snakemake.utils import min_version, validate

min_version("9.0")


configfile: "config/config.yaml"


validate(config, "workflow/schemas/config.schema.yaml")


include: "workflow/rules/common.smk"
include: "workflow/rules/campaign.smk"
include: "workflow/rules/folds.smk"
include: "workflow/rules/aggregate.smk"
include: "workflow/rules/final.smk"
include: "workflow/rules/track.smk"
include: "workflow/rules/diagnosis.smk"


localrules:
    all,
    campaign,
    aggregate,
    tables,
    summary_figure,
    track,


rule all:
    input:
        all_outputs,
    default_target: True
