rule dataset_seed:
    """One phantom seed of the training set: its phantom and randomised render."""
    output:
        directory(f"{DATASET_DIR}/seed_{{seed}}"),
    log:
        f"{RESULTS}/logs/dataset/seed_{{seed}}.log",
    params:
        out=lambda wc, output: os.path.dirname(output[0]),
        opts=dataset_options,
    threads: 2
    conda:
        ENV
    resources:
        mem_mb=MEM_MB,
    shell:
        "python -m sim dataset --seeds {wildcards.seed} --out {params.out:q} --no-index "
        "{params.opts} --quiet > {log:q} 2>&1"


rule dataset:
    """The training set's index and card over every seed (config dataset.seeds)."""
    input:
        dataset_renders,
    output:
        index=f"{DATASET_DIR}/dataset.json",
        card=f"{DATASET_DIR}/dataset_card.json",
    log:
        f"{RESULTS}/logs/dataset/index.log",
    params:
        out=lambda wc, output: os.path.dirname(output.index),
        seeds=lambda wc: DATASET["seeds"],
        opts=dataset_options,
    threads: 1
    conda:
        ENV
    shell:
        "python -m sim dataset --seeds {params.seeds:q} --out {params.out:q} --resume "
        "{params.opts} --quiet > {log:q} 2>&1"
