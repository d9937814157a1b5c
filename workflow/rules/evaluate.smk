rule evaluate_step:
    input:
        manifest=rules.phantom.output.manifest,
        index=rules.render.output.index,
        meshes=lambda wc: [method_mesh(wc, m) for m in eval_methods(wc)],
        models=lambda wc: [method_mesh(wc, m).replace("mesh.ply", "model.npz") for m in eval_methods(wc)],
        preop_models=lambda wc: [method_preop_model(wc, m) for m in eval_methods(wc)],
        masks=lambda wc: [
            f"{RESULTS}/seed_{wc.seed}/{wc.variant}/{m}/step_{wc.step}/change_masks.npz"
            for m in mask_methods(wc)
        ],
        start_models=lambda wc: [previous_model(wc, m) for m in mask_methods(wc)],
    output:
        metrics=f"{RESULTS}/seed_{{seed}}/{{variant}}/eval/step_{{step}}.json",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/{{variant}}/evaluate_step_{{step}}.log",
    params:
        methods=eval_methods,
        mask_methods=mask_methods,
        eval_sequence=lambda wc: f"{RESULTS}/seed_{wc.seed}/render/eval/step_{wc.step}",
        change_sequence=lambda wc: f"{RESULTS}/seed_{wc.seed}/render/step_{wc.step}",
    threads: 1
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    script:
        "../scripts/evaluate_step.py"


rule seed_table:
    input:
        variant_steps,
    output:
        metrics=f"{RESULTS}/seed_{{seed}}/{{variant}}/metrics.json",
        csv=f"{RESULTS}/seed_{{seed}}/{{variant}}/metrics.csv",
        md=f"{RESULTS}/seed_{{seed}}/{{variant}}/metrics.md",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/{{variant}}/table.log",
    params:
        experiment=lambda wc: f"{config['experiment']}/seed_{wc.seed}/{wc.variant}",
    threads: 1
    conda:
        ENV
    shell:
        "python -m chisel evaluate table --inputs {input:q} --experiment {params.experiment:q} "
        "--out-dir \"$(dirname {output.metrics:q})\" > {log:q} 2>&1"


rule experiment_metrics:
    """The main experiment's table: the first seed's paper table (Table 1 layout)."""
    input:
        f"{RESULTS}/seed_{SEEDS[0]}/base/metrics.json",
    output:
        f"{RESULTS}/metrics.json",
    log:
        f"{RESULTS}/logs/experiment_metrics.log",
    threads: 1
    conda:
        ENV
    shell:
        "cp {input:q} {output:q}.tmp && mv {output:q}.tmp {output:q} 2> {log:q}"


rule seeds_table:
    """Table 1 over several phantoms (config table_seeds): mean and spread per step and method."""
    input:
        expand(f"{RESULTS}/seed_{{seed}}/base/metrics.json", seed=TABLE_SEEDS),
    output:
        f"{RESULTS}/table/metrics_seeds.json",
    log:
        f"{RESULTS}/logs/seeds_table.log",
    params:
        labels=[f"seed_{s}" for s in TABLE_SEEDS],
    threads: 1
    conda:
        ENV
    shell:
        "python -m chisel evaluate seeds --inputs {input:q} --labels {params.labels:q} "
        "--out-dir \"$(dirname {output:q})\" > {log:q} 2>&1"


rule sweep:
    input:
        lambda wc: expand(
            f"{RESULTS}/seed_{SEEDS[0]}/{{variant}}/metrics.json", variant=sweep_variants(wc.kind)
        ),
    output:
        csv=f"{RESULTS}/sweeps/{{kind}}.csv",
    log:
        f"{RESULTS}/logs/sweep_{{kind}}.log",
    wildcard_constraints:
        kind="seqlen|posenoise|depthnoise",
    params:
        runs=lambda wc, input: [
            f"{v}={p}" for v, p in zip(SWEEPS.get(wc.kind, []), input, strict=True)
        ],
        param=lambda wc: SWEEP_PARAMS[wc.kind],
    threads: 1
    conda:
        ENV
    shell:
        "python -m chisel evaluate sweep --param {params.param} --run {params.runs:q} "
        "--out {output.csv:q} > {log:q} 2>&1"


rule panels:
    """Figure-4-style panels per step: frame, preop/GT/estimated/updated depth, change mask."""
    input:
        index=f"{RESULTS}/seed_{SEEDS[0]}/render/render.json",
        preop=f"{RESULTS}/seed_{SEEDS[0]}/preop/mesh.ply",
        updated=expand(f"{RESULTS}/seed_{SEEDS[0]}/base/updated/step_{{step}}/mesh.ply", step=[step_str(s) for s in STEPS]),
        masks=expand(f"{RESULTS}/seed_{SEEDS[0]}/base/updated/step_{{step}}/change_masks.npz", step=[step_str(s) for s in STEPS]),
        pred=expand(f"{RESULTS}/seed_{SEEDS[0]}/depth/pred/step_{{step}}", step=[step_str(s) for s in STEPS]),
    output:
        panels=f"{RESULTS}/report/panels.npz",
    log:
        f"{RESULTS}/logs/panels.log",
    params:
        steps=STEPS,
    threads: 1
    conda:
        ENV
    script:
        "../scripts/panels.py"


rule report:
    input:
        metrics=f"{RESULTS}/metrics.json",
        panels=rules.panels.output.panels,
        preop=f"{RESULTS}/seed_{SEEDS[0]}/preop/mesh.ply",
        updated=f"{RESULTS}/seed_{SEEDS[0]}/base/updated/step_{BITES:02d}/mesh.ply",
        manifest=f"{RESULTS}/seed_{SEEDS[0]}/phantom/phantom.json",
        sweeps=lambda wc: list(report_sweeps(wc).values()),
        ct_slices=expand(f"{RESULTS}/seed_{SEEDS[0]}/base/export/step_{{step}}_slices.npz", step=[step_str(s) for s in STEPS]),
    output:
        html=f"{RESULTS}/report.html",
    log:
        f"{RESULTS}/logs/report.log",
    params:
        # "--sweep K=CSV ..." quoted for the shell, or nothing without sweeps.
        sweeps=lambda wc: " ".join(
            shlex.quote(o)
            for o in (["--sweep", *(f"{k}={v}" for k, v in report_sweeps(wc).items())]
                      if report_sweeps(wc) else [])
        ),
        title=f"Endoscopic Chisel: experiment {config['experiment']}",
    threads: 1
    conda:
        ENV
    shell:
        "ROI=$(python -c \"import json,sys; b=json.load(open(sys.argv[1]))['roi_box_mm']; "
        "print(','.join(str(v) for c in b for v in c))\" {input.manifest:q}) && "
        "python -m chisel report --metrics {input.metrics:q} --panels {input.panels:q} "
        "--preop-mesh {input.preop:q} --updated-mesh {input.updated:q} --roi=$ROI "
        "--ct-slices {input.ct_slices:q} "
        "{params.sweeps} "
        "--title {params.title:q} --out {output.html:q} > {log:q} 2>&1"


# Experiment targets (see README): the paper's table over seeds, and the three sweeps.
rule table:
    input:
        rules.seeds_table.output,


rule seqlen:
    input:
        f"{RESULTS}/sweeps/seqlen.csv",


rule posenoise:
    input:
        f"{RESULTS}/sweeps/posenoise.csv",


rule depthnoise:
    input:
        f"{RESULTS}/sweeps/depthnoise.csv",
