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
        "python -m chisel update --model {input.model} --sequence {params.seq} {params.opts} "
        "--out {output.model} --report {output.report} --masks {output.masks} > {log} 2>&1"


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
        "python -m chisel mesh --model {input.model} --out {output.mesh} > {log} 2>&1"
