UC = config.get("update", {})


def update_sequence(wc):
    """The intraoperative sequence the updater reads (tracked poses + frames)."""
    if wc.variant.startswith("posenoise-"):
        noise = wc.variant.split("-", 1)[1]
        return f"{RESULTS}/seed_{wc.seed}/retrack/{noise}/step_{wc.step}"
    return f"{RESULTS}/seed_{wc.seed}/render/step_{wc.step}"


def previous_model(wc):
    step = int(wc.step)
    if step == 1:
        return f"{RESULTS}/seed_{wc.seed}/preop/model.npz"
    return f"{RESULTS}/seed_{wc.seed}/{wc.variant}/{wc.method}/step_{step - 1:02d}/model.npz"


def update_inputs(wc):
    inputs = {
        "model": previous_model(wc),
        "index": f"{RESULTS}/seed_{wc.seed}/render/render.json",
    }
    if wc.variant.startswith("posenoise-"):
        inputs["seq"] = update_sequence(wc)
    if METHOD_SPECS[wc.method][0] == "network":
        inputs["pred"] = f"{RESULTS}/seed_{wc.seed}/depth/pred/step_{wc.step}"
    return inputs


def update_options(wc, input):
    depth, registration = METHOD_SPECS[wc.method]
    opts = [f"--threshold-mm {UC.get('threshold_mm', 1.0)}"]
    opts.append(f"--depth-source sequence:{input.pred}" if depth == "network" else "--depth-source gt")
    if not registration:
        opts.append("--no-registration")
    kind, _, value = wc.variant.partition("-")
    if kind == "seqlen":
        opts.append(f"--max-frames {value}")
    if kind == "depthnoise":
        opts.append(f"--depth-noise-mm {value} --depth-noise-seed {wc.seed}")
    return " ".join(opts)


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
    resources:
        mem_mb=MEM_MB,
    shell:
        "{PY} -m chisel update --model {input.model} --sequence {params.seq} {params.opts} "
        "--out {output.model} --report {output.report} --masks {output.masks} > {log} 2>&1"


rule mesh:
    input:
        model="{path}/model.npz",
    output:
        mesh="{path}/mesh.ply",
    log:
        "{path}/mesh.log",
    threads: 1
    shell:
        "{PY} -m chisel mesh --model {input.model} --out {output.mesh} > {log} 2>&1"
