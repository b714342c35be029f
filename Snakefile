# parammap workflow: bracketed photos -> HDR frames -> calibrated poses -> observation
# map -> parameter maps and reports. All logic lives in the parammap package; rules
# call its CLI. Paths follow docs/reference/outputs.md (see README).

from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/capture.smk"
include: "workflow/rules/hdr.smk"
include: "workflow/rules/observation.smk"
include: "workflow/rules/fit.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/paper.smk"


rule all:
    input:
        all_targets(),
    default_target: True
