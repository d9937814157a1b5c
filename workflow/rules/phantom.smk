rule phantom:
    output:
        manifest=f"{RESULTS}/seed_{{seed}}/phantom/phantom.json",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/phantom.log",
    params:
        bites=BITES,
        procedure=config["phantom"].get("procedure", "uncinectomy"),
        opts=" ".join(
            f"--{flag} {config['phantom'][key]}"
            for key, flag in [
                ("ct_spacing_mm", "spacing-mm"),
                ("mucosa_mm", "mucosa-mm"),
                ("mesh_edge_mm", "mesh-edge-mm"),
            ]
            if key in config["phantom"]
        ),
    threads: 1
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m phantoms generate --seed {wildcards.seed} --procedure {params.procedure:q} "
        "--bites {params.bites} "
        "{params.opts} --out \"$(dirname {output.manifest:q})\" > {log:q} 2>&1"
