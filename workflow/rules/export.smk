# Updated CTs: one per step and method (chisel export-ct), and their Dice of the removed
# region against the step's true label CT (one small JSON per step, read by the report).

EXPORT_METHODS = list(config["methods"])


def export_model(wc):
    if wc.method == "no_update":
        return f"{RESULTS}/seed_{wc.seed}/preop/model.npz"
    return f"{RESULTS}/seed_{wc.seed}/base/{wc.method}/step_{wc.step}/model.npz"


rule export_ct:
    """The preoperative HU CT with the tissue the method's model removed set to air."""
    input:
        manifest=rules.phantom.output.manifest,
        model=export_model,
    output:
        ct=f"{RESULTS}/seed_{{seed}}/base/export/{{method}}/step_{{step}}_hu.nii.gz",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/export/{{method}}_step_{{step}}.log",
    wildcard_constraints:
        method="[a-z_]+",
        step="[0-9]+",
    threads: 1
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m chisel export-ct --model {input.model} "
        "--ct $(dirname {input.manifest})/ct/step_00_hu.nii.gz --out {output.ct} > {log} 2>&1"


rule ct_dice:
    """Updated-CT Dice of the removed region, every method, one step."""
    input:
        manifest=rules.phantom.output.manifest,
        cts=lambda wc: [
            f"{RESULTS}/seed_{wc.seed}/base/export/{m}/step_{wc.step}_hu.nii.gz"
            for m in EXPORT_METHODS
        ],
    output:
        f"{RESULTS}/seed_{{seed}}/base/export/step_{{step}}.json",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/export/dice_step_{{step}}.log",
    wildcard_constraints:
        step="[0-9]+",
    params:
        methods=EXPORT_METHODS,
    threads: 1
    conda:
        ENV
    script:
        "../scripts/ct_dice.py"


rule ct_exports:
    """Target: every updated CT and its Dice for the first seed."""
    input:
        expand(
            f"{RESULTS}/seed_{SEEDS[0]}/base/export/step_{{step}}.json",
            step=[step_str(s) for s in STEPS],
        ),
