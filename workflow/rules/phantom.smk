rule phantom:
    output:
        manifest=f"{RESULTS}/seed_{{seed}}/phantom/phantom.json",
    log:
        f"{RESULTS}/logs/seed_{{seed}}/phantom.log",
    params:
        bites=BITES,
        spacing=config["phantom"].get("ct_spacing_mm", 0.5),
    threads: 1
    resources:
        mem_mb=MEM_MB,
    shell:
        "{PY} -m phantoms generate --seed {wildcards.seed} --bites {params.bites} "
        "--ct-spacing-mm {params.spacing} --out $(dirname {output.manifest}) > {log} 2>&1"
