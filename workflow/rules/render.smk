rule sim_config:
    """The experiment's simulator configuration as one YAML file (sim render --config)."""
    output:
        SIM_CONFIG,
    log:
        f"{RESULTS}/logs/sim_config.log",
    params:
        mapping=RC.get("sim", {}),
    conda:
        ENV
    script:
        "../scripts/write_yaml.py"


rule render:
    input:
        manifest=rules.phantom.output.manifest,
        sim_config=SIM_CONFIG,
    output:
        index=f"{RESULTS}/seed_{{seed}}/render/render.json",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/render.log",
    params:
        opts=(
            f"--width {RC['width']} --height {RC['height']} --frames {RC['frames']} "
            f"--preop-frames {RC['preop_frames']} --eval-poses {RC['eval_poses']} "
            f"--spp {RC.get('spp', 16)} --pose-noise-mm {RC.get('pose_noise_mm', 0.0)} "
            f"--pose-noise-deg {RC.get('pose_noise_deg', 0.0)}"
            + (" --tools" if RC.get("tools", False) else "")
        ),
    threads: 2
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m sim render --phantom \"$(dirname {input.manifest:q})\" --out \"$(dirname {output.index:q})\" "
        "--seed {wildcards.seed} --config {input.sim_config:q} {params.opts} > {log:q} 2>&1"


rule retrack:
    """Tracked poses with another amount of tracking noise (pose-noise sweep); same frames."""
    input:
        index=rules.render.output.index,
    output:
        seq=directory(f"{RESULTS}/seed_{{seed}}/retrack/{{noise}}/step_{{step}}"),
    log:
        f"{RESULTS}/logs/seed_{{seed}}/retrack_{{noise}}_step_{{step}}.log",
    wildcard_constraints:
        noise=r"[0-9.]+",
    params:
        # Noise level X: a constant hand-eye error of X mm and X degrees plus per-frame
        # jitter of X/4 mm and X/4 degrees per axis; 0 = exact poses.
        jitter=lambda wc: float(wc.noise) / 4.0,
    threads: 1
    conda:
        ENV
    shell:
        "python -m sim retrack --sequence \"$(dirname {input.index:q})/step_{wildcards.step}\" "
        "--handeye-mm {wildcards.noise} --handeye-deg {wildcards.noise} "
        "--jitter-mm {params.jitter} --jitter-deg {params.jitter} "
        "--seed {wildcards.seed} --out {output.seq:q} > {log:q} 2>&1"
