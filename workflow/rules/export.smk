# Updated CTs: one per step and method (chisel export-ct), and their Dice of the removed
# region against the step's true label CT (one small JSON per step, read by the report).

EXPORT_METHODS = list(config["methods"])


rule export_ct:
    """The preoperative HU CT with the tissue the method's update removed set to air
    (--preop-model: CT detail the preoperative model could not hold is kept)."""
    input:
        manifest=rules.phantom.output.manifest,
        # no_update: the preop model itself; else the method's model after the step
        model=lambda wc: (
            f"{RESULTS}/seed_{wc.seed}/preop/model.npz"
            if wc.method == "no_update"
            else f"{RESULTS}/seed_{wc.seed}/base/{wc.method}/step_{wc.step}/model.npz"
        ),
        # the preoperative model the method's updates started from (its own build)
        preop=lambda wc: (
            f"{RESULTS}/seed_{wc.seed}/preop/"
            + ("model_sweep.npz" if wc.method == "updated_sweep" else "model.npz")
        ),
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
        "python -m chisel export-ct --model {input.model:q} --preop-model {input.preop:q} "
        "--ct \"$(dirname {input.manifest:q})/ct/step_00_hu.nii.gz\" --out {output.ct:q} > {log:q} 2>&1"


rule ct_dice:
    """Updated-CT Dice of the removed region, every method, one step, and the report's
    axial and coronal slices through the change box (before, truth, each method)."""
    input:
        manifest=rules.phantom.output.manifest,
        cts=lambda wc: [
            f"{RESULTS}/seed_{wc.seed}/base/export/{m}/step_{wc.step}_hu.nii.gz"
            for m in EXPORT_METHODS
        ],
    output:
        dice=f"{RESULTS}/seed_{{seed}}/base/export/step_{{step}}.json",
        slices=f"{RESULTS}/seed_{{seed}}/base/export/step_{{step}}_slices.npz",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/export/dice_step_{{step}}.log",
    wildcard_constraints:
        step="[0-9]+",
    params:
        methods=EXPORT_METHODS,
    threads: 1
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    script:
        "../scripts/ct_dice.py"


rule ct_exports:
    """Target: every updated CT and its Dice for the first seed."""
    input:
        expand(
            f"{RESULTS}/seed_{SEEDS[0]}/base/export/step_{{step}}.json",
            step=[step_str(s) for s in STEPS],
        ),
