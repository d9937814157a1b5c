import sys

from snakemake.utils import validate

configfile: "config/config.yaml"


validate(config, "../schemas/config.schema.yaml")

PY = sys.executable  # the interpreter running Snakemake: the project's virtual environment
RESULTS = f"results/{config['experiment']}"
SEEDS = [int(s) for s in config["seeds"]]
TABLE_SEEDS = [int(s) for s in config.get("table_seeds", SEEDS)]
BITES = int(config["phantom"]["bites"])
STEPS = list(range(1, BITES + 1))
MEM_MB = int(config.get("resources", {}).get("mem_mb", 8000))
SWEEPS = config.get("sweeps", {})
UPDATE_METHODS = [m for m in config["methods"] if m != "no_update"]

# How each updated method runs the updater: (depth source, registration on?).
# "exact_noreg" exists for the pose-noise sweep (exact depth, registration off).
METHOD_SPECS = {
    "updated": ("network", True),
    "depth_ablation": ("gt", True),
    "registration_ablation": ("network", False),
    "exact_noreg": ("gt", False),
}

# Methods run per variant: "base" is the paper's table; the rest are the sweeps.
def variant_methods(variant):
    if variant == "base":
        return UPDATE_METHODS
    kind = variant.split("-", 1)[0]
    return {
        "seqlen": ["updated", "depth_ablation"],
        "posenoise": ["depth_ablation", "exact_noreg"],
        "depthnoise": ["depth_ablation"],
    }[kind]


def sweep_variants(kind):
    return [f"{kind}-{v}" for v in SWEEPS.get(kind, [])]


wildcard_constraints:
    seed=r"\d+",
    step=r"\d\d",
    variant=r"base|seqlen-\d+|posenoise-[0-9.]+|depthnoise-[0-9.]+",
    method="|".join(METHOD_SPECS),


def step_str(step):
    return f"{int(step):02d}"
