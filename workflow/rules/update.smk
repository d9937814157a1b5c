rule update_config:
    """The experiment's update parameters as one YAML file (chisel update --config)."""
    output:
        UPDATE_CONFIG,
    log:
        f"{RESULTS}/logs/update_config.log",
    params:
        mapping=config.get("update", {}),
    conda:
        ENV
    script:
        "../scripts/write_yaml.py"


rule update:
    """One surgical step of the paper's update: change detection + masked TSDF update."""
    input:
        unpack(update_inputs),
    output:
        model=f"{RESULTS}/seed_{{seed}}/{{variant}}/{{method}}/step_{{step}}/model.npz",
        report=f"{RESULTS}/seed_{{seed}}/{{variant}}/{{method}}/step_{{step}}/update.json",
        masks=f"{RESULTS}/seed_{{seed}}/{{variant}}/{{method}}/step_{{step}}/change_masks.npz",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/{{variant}}/{{method}}/update_step_{{step}}.log",
    params:
        seq=update_sequence,
        opts=update_options,
    threads: 2
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m chisel update --model {input.model:q} --sequence {params.seq:q} {params.opts} "
        "--out {output.model:q} --report {output.report:q} --masks {output.masks:q} > {log:q} 2>&1"


rule mesh:
    input:
        model="{path}/model.npz",
    output:
        mesh="{path}/mesh.ply",
    log:
        "{path}/mesh.log",
    threads: 1
    conda:
        ENV
    shell:
        "python -m chisel mesh --model {input.model:q} --out {output.mesh:q} > {log:q} 2>&1"


rule external_depth:
    """A researcher's own depth estimator (config depth.extra) on one step's sequence."""
    input:
        unpack(extra_depth_inputs),
    output:
        directory(f"{RESULTS}/seed_{{seed}}/depth/extra/{{extra}}/step_{{step}}"),
    log:
        f"{RESULTS}/logs/seed_{{seed}}/external_depth_{{extra}}_step_{{step}}.log",
    wildcard_constraints:
        extra="|".join(EXTRA_DEPTH) or "(?!)",
    params:
        seq=lambda wc, input: f"{os.path.dirname(input.index)}/step_{wc.step}",
        opts=extra_depth_options,
    threads: 1
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m chisel external-depth --sequence {params.seq:q} --out {output:q} {params.opts} "
        "> {log:q} 2>&1"
