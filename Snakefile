# Endoscopic Chisel: end-to-end synthetic benchmark of intraoperative model updating.
#
#   snakemake --cores 2                              # default experiment (config/config.yaml)
#   snakemake --cores 2 --configfile config/smoke.yaml
#   snakemake --cores 2 table | seqlen | posenoise | depthnoise | report
#   snakemake --cores 2 dataset --config dataset='{seeds: "1000-1099"}'   # training set
#
# Stages: phantom -> renders -> CT segmentation surface -> preop model -> update per bite
# -> score -> report. Every rule calls a CLI of this project; outputs live under
# results/<experiment>/. See docs/workflow.md.

include: "workflow/rules/common.smk"
include: "workflow/rules/phantom.smk"
include: "workflow/rules/render.smk"
include: "workflow/rules/preop.smk"
include: "workflow/rules/update.smk"
include: "workflow/rules/change_aware.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/export.smk"
include: "workflow/rules/dataset.smk"


rule all:
    default_target: True
    input:
        f"{RESULTS}/metrics.json",
        f"{RESULTS}/report.html",
        rules.ct_exports.input,
