# The change-aware depth network's row (method "change_aware", issue 20), beside the
# paper's monocular network ("updated", which keeps its row). Active when "change_aware"
# is listed in config "methods". Per seed: the shipped change-aware checkpoint is
# fine-tuned on the preop sequence (prior and target: the CT surface, or the preop model's
# surface as the updater renders it (depth.change_aware_finetune_prior), at the tracked
# poses, synthetic removals put into the priors; docs/depth.md), then every step
# runs the updater with
# --depth-source change-aware:CKPT (the model's own render M_t is the network's prior;
# registration on, as for "updated"). Its paths use the literal method name, so the
# generic `update` rule (methods of METHOD_SPECS) never matches them. Its input functions
# live in common.smk.


# depth.change_aware_finetune_prior (schema default ct_surface): the prior the network is
# fine-tuned on, the CT surface mesh or the preop model whose surface the updater renders
# as M_t (docs/depth.md: measured neutral to slightly worse, so not the default).
if DC.get("change_aware_finetune_prior", "ct_surface") == "model":
    CA_FINETUNE_PRIOR, CA_FINETUNE_FLAG = rules.preop_model.output.model, "--model"
else:
    CA_FINETUNE_PRIOR, CA_FINETUNE_FLAG = rules.ct_surface.output.mesh, "--mesh"


rule finetune_change_aware:
    """Per-patient fine-tuning of the change-aware network on the preop sequence."""
    input:
        index=rules.render.output.index,
        prior=CA_FINETUNE_PRIOR,
        base=change_aware_base_checkpoint(),
    output:
        ckpt=f"{RESULTS}/seed_{{seed}}/depth/change_aware_finetuned.pt",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/finetune_change_aware.log",
    params:
        steps=DC.get("change_aware_finetune_steps", 60),
        prior_flag=CA_FINETUNE_FLAG,
        seed=finetune_seed,
    threads: 2
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m chisel depth finetune --kind change-aware --checkpoint {input.base:q} "
        "--sequence \"$(dirname {input.index:q})/preop\" {params.prior_flag} {input.prior:q} --steps {params.steps} "
        "--seed {params.seed} --threads {threads} --out {output.ckpt:q} > {log:q} 2>&1"


rule update_change_aware:
    """One surgical step with the change-aware network as the depth source."""
    input:
        model=change_aware_previous,
        index=rules.render.output.index,
        ckpt=change_aware_checkpoint,
        config=UPDATE_CONFIG,
    output:
        model=f"{RESULTS}/seed_{{seed}}/base/change_aware/step_{{step}}/model.npz",
        report=f"{RESULTS}/seed_{{seed}}/base/change_aware/step_{{step}}/update.json",
        masks=f"{RESULTS}/seed_{{seed}}/base/change_aware/step_{{step}}/change_masks.npz",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/base/change_aware/update_step_{{step}}.log",
    threads: 2
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m chisel update --model {input.model:q} "
        "--sequence \"$(dirname {input.index:q})/step_{wildcards.step}\" --config {input.config:q} "
        "--allow-unused-step "
        "--depth-source change-aware:{input.ckpt:q} "
        "--out {output.model:q} --report {output.report:q} --masks {output.masks:q} > {log:q} 2>&1"
