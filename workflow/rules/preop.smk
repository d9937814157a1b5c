rule ct_surface:
    """CT segmentation surface from the preoperative CT volume (as a user with real CT would)."""
    input:
        manifest=rules.phantom.output.manifest,
    output:
        mesh=f"{RESULTS}/seed_{{seed}}/preop/ct_surface.ply",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/ct_surface.log",
    threads: 1
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m chisel ct-surface --ct \"$(dirname {input.manifest:q})/ct/step_00_hu.nii.gz\" "
        "--out {output.mesh:q} > {log:q} 2>&1"


rule preop_model:
    """The preoperative model from the whole CT (issue 19): the step-0 HU volume's signed
    distance over the grid, the preop sweep adding weight; `model.max_miss_fraction`
    bounds the preop rays that may leave the CT's field of view."""
    input:
        manifest=rules.phantom.output.manifest,
        index=rules.render.output.index,
    output:
        model=f"{RESULTS}/seed_{{seed}}/preop/model.npz",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/preop_model.log",
    params:
        opts=f"--voxel-size-mm {MC['voxel_size_mm']} --trunc-mm {MC['trunc_mm']} "
        f"--max-miss-fraction {MC.get('max_miss_fraction', 0.05)}",
    threads: 2
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m chisel build --from-ct \"$(dirname {input.manifest:q})/ct/step_00_hu.nii.gz\" "
        "--sequence \"$(dirname {input.index:q})/preop\" {params.opts} --no-progress "
        "--out {output.model:q} > {log:q} 2>&1"


rule preop_model_sweep:
    """The paper's preoperative model: the CT surface rendered at the preop poses, fused."""
    input:
        surface=rules.ct_surface.output.mesh,
        index=rules.render.output.index,
    output:
        model=f"{RESULTS}/seed_{{seed}}/preop/model_sweep.npz",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/preop_model_sweep.log",
    params:
        opts=f"--voxel-size-mm {MC['voxel_size_mm']} --trunc-mm {MC['trunc_mm']}",
    threads: 2
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m chisel build --surface {input.surface:q} --sequence \"$(dirname {input.index:q})/preop\" "
        "{params.opts} --no-progress --out {output.model:q} > {log:q} 2>&1"


rule preop_ct_depth:
    """The preop frames with the CT surface rendered at the tracked poses: fine-tuning labels."""
    input:
        surface=rules.ct_surface.output.mesh,
        index=rules.render.output.index,
    output:
        seq=directory(f"{RESULTS}/seed_{{seed}}/preop/ct_depth_sequence"),
    log:
        f"{RESULTS}/logs/seed_{{seed}}/preop_ct_depth.log",
    threads: 1
    conda:
        ENV
    shell:
        "python -m chisel render-depth --mesh {input.surface:q} --sequence \"$(dirname {input.index:q})/preop\" "
        "--out {output.seq:q} > {log:q} 2>&1"


rule finetune:
    """Per-patient fine-tuning of the depth network on the preop sequence (as the paper does)."""
    input:
        seq=rules.preop_ct_depth.output.seq,
        base=base_checkpoint(),
    output:
        ckpt=f"{RESULTS}/seed_{{seed}}/depth/finetuned.pt",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/finetune.log",
    params:
        epochs=DC.get("finetune_epochs", 3),
        enabled=DC.get("finetune", True),
        seed=finetune_seed,
    threads: 2
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m chisel depth finetune --checkpoint {input.base:q} --sequence {input.seq:q} --epochs {params.epochs} "
        "--seed {params.seed} --threads {threads} --out {output.ckpt:q} > {log:q} 2>&1"


rule predict_depth:
    input:
        index=rules.render.output.index,
        ckpt=network_checkpoint,
    output:
        seq=directory(f"{RESULTS}/seed_{{seed}}/depth/pred/step_{{step}}"),
    log:
        f"{RESULTS}/logs/seed_{{seed}}/predict_step_{{step}}.log",
    params:
        ckpt=lambda wc, input: input.ckpt if input.ckpt else base_checkpoint(),
    threads: 2
    conda:
        ENV
    shell:
        "python -m chisel depth predict --checkpoint {params.ckpt:q} --sequence \"$(dirname {input.index:q})/step_{wildcards.step}\" "
        "--out {output.seq:q} > {log:q} 2>&1"
