import os
import shlex
import sys

from snakemake.utils import validate

# Relative to the Snakefile, so `snakemake -s PATH/Snakefile -d OTHER_DIR` works.
configfile: os.path.join(workflow.basedir, "config", "config.yaml")


validate(config, "../schemas/config.schema.yaml")

# Rules call `python -m ...`: the interpreter running Snakemake (the project's .venv) comes
# first on PATH, and the repository on PYTHONPATH, also for jobs on other executors.
os.environ.update(
    PATH=os.pathsep.join([os.path.dirname(sys.executable), os.environ.get("PATH", "")]),
    PYTHONPATH=os.pathsep.join(p for p in (workflow.basedir, os.environ.get("PYTHONPATH")) if p),
)
ENV = "../envs/chisel.yaml"
RESULTS = f"results/{config['experiment']}"
SEEDS = [int(s) for s in config["seeds"]]
if len(SEEDS) != 1:
    # The default target, sweeps and report describe one phantom; a second seed used to be
    # silently ignored. Several phantoms are the `table` target's job.
    raise ValueError(
        f"config seeds: {config['seeds']}: `seeds` is the one phantom seed of the default "
        "target (metrics.json, report, sweeps); list several seeds under `table_seeds` and "
        "run `snakemake table` to evaluate and aggregate them"
    )
TABLE_SEEDS = [int(s) for s in config.get("table_seeds", SEEDS)]
BITES = int(config["phantom"]["bites"])
STEPS = list(range(1, BITES + 1))
MEM_MB = int(config.get("resources", {}).get("mem_mb", 8000))
SWEEPS = config.get("sweeps", {})
UPDATE_METHODS = [m for m in config["methods"] if m != "no_update"]
# Researchers' own depth estimators (config depth.extra): one method row each, run like
# "updated" (registration on) on the depth that `chisel external-depth` writes.
EXTRA_DEPTH = dict(config.get("depth", {}).get("extra") or {})

# How each updated method runs the updater: (depth source, registration on?).
# "exact_noreg" exists for the pose-noise sweep (exact depth, registration off).
METHOD_SPECS = {
    "updated": ("network", True),
    "depth_ablation": ("gt", True),
    "registration_ablation": ("network", False),
    "exact_noreg": ("gt", False),
    "updated_sweep": ("network", True),  # the paper's build: preop model from the sweep alone
}
_taken = set(METHOD_SPECS) | {"no_update", "change_aware"}
if set(EXTRA_DEPTH) & _taken:
    raise ValueError(
        f"config depth.extra: {sorted(set(EXTRA_DEPTH) & _taken)} is the name of a built-in "
        "method; name your estimator otherwise"
    )
METHOD_SPECS.update({name: ("extra", True) for name in EXTRA_DEPTH})
UPDATE_METHODS += list(EXTRA_DEPTH)

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


MC = config["model"]


DC = config.get("depth", {})


def finetune_seed(wildcards):
    """The seed of a phantom's per-patient fine-tunings: the phantom seed, plus
    config depth.finetune_seed_offset (a second value measures the rows' own spread)."""
    return int(wildcards.seed) + int(DC.get("finetune_seed_offset", 0))


def base_checkpoint():
    """The configured depth checkpoint; "default" is the one shipped with the package."""
    if DC.get("checkpoint", "default") == "default":
        from chisel.depth import DEFAULT_CHECKPOINT

        return str(DEFAULT_CHECKPOINT)
    return DC["checkpoint"]


def network_checkpoint(wildcards):
    return rules.finetune.output.ckpt.format(seed=wildcards.seed) if DC.get("finetune", True) else []


# The ``update:`` section as the file that ``chisel update --config`` reads (written by the
# update_config rule):
# UpdateConfig's fields, checked by chisel, whose defaults are the dataclass's own.
UPDATE_CONFIG = f"{RESULTS}/update_config.yaml"
# The ``render.sim:`` section as the file that ``sim render --config`` reads (sim_config rule).
SIM_CONFIG = f"{RESULTS}/sim_config.yaml"


def update_sequence(wc):
    """The intraoperative sequence the updater reads (tracked poses + frames)."""
    if wc.variant.startswith("posenoise-"):
        noise = wc.variant.split("-", 1)[1]
        return f"{RESULTS}/seed_{wc.seed}/retrack/{noise}/step_{wc.step}"
    return f"{RESULTS}/seed_{wc.seed}/render/step_{wc.step}"


def previous_model(wc, method=None):
    # The model a method's step began from (its update's input; its change masks are
    # scored against it).
    method = method or wc.method
    step = int(wc.step)
    if step == 1:
        return method_preop_model(wc, method)
    return f"{RESULTS}/seed_{wc.seed}/{wc.variant}/{method}/step_{step - 1:02d}/model.npz"


def update_inputs(wc):
    inputs = {
        "model": previous_model(wc),
        "index": f"{RESULTS}/seed_{wc.seed}/render/render.json",
        "config": UPDATE_CONFIG,
    }
    if wc.variant.startswith("posenoise-"):
        inputs["seq"] = update_sequence(wc)
    if METHOD_SPECS[wc.method][0] == "network":
        inputs["pred"] = f"{RESULTS}/seed_{wc.seed}/depth/pred/step_{wc.step}"
    if METHOD_SPECS[wc.method][0] == "extra":
        inputs["pred"] = f"{RESULTS}/seed_{wc.seed}/depth/extra/{wc.method}/step_{wc.step}"
    return inputs


def update_options(wc, input):
    depth, registration = METHOD_SPECS[wc.method]
    # A step whose frames all fail registration is scored as "no update", not a crash.
    opts = ["--config", str(input.config), "--allow-unused-step", "--depth-source"]
    opts.append("gt" if depth == "gt" else f"sequence:{input.pred}")
    if depth == "gt":
        # The shading's pose correction is a cue for estimates: exact depth registers to the
        # model by itself, and the correction cost its row 3 % (docs/results.md, fortieth).
        opts.append("--no-align-by-shading")
    if not registration:
        opts.append("--no-register")
    kind, _, value = wc.variant.partition("-")
    if kind == "seqlen":
        opts += ["--max-frames", value]
    if kind == "depthnoise":
        opts += ["--depth-noise-mm", value, "--depth-noise-seed", str(wc.seed)]
    # Every value is quoted for the shell, as in extra_depth_options and dataset_options.
    return " ".join(shlex.quote(o) for o in opts)


def method_mesh(wc, method):
    step = int(wc.step)
    if method == "no_update" or step == 0:
        return f"{RESULTS}/seed_{wc.seed}/preop/mesh.ply"
    return f"{RESULTS}/seed_{wc.seed}/{wc.variant}/{method}/step_{wc.step}/mesh.ply"


def method_preop_model(wc, method):
    # The model a method's steps started from: the sweep-only build has its own grid.
    build = "model_sweep" if method == "updated_sweep" else "model"
    return f"{RESULTS}/seed_{wc.seed}/preop/{build}.npz"


def eval_methods(wc):
    if int(wc.step) == 0:
        return ["updated"]  # the paper's "preop" row: the preoperative model, before any update
    methods = variant_methods(wc.variant)
    return (["no_update"] if wc.variant == "base" and "no_update" in config["methods"] else []) + methods


def mask_methods(wc):
    # Change masks are scored on the full sequence of the base experiment only.
    if int(wc.step) == 0 or wc.variant != "base":
        return []
    return [m for m in eval_methods(wc) if m != "no_update"]


def variant_steps(wc):
    steps = [0] + STEPS if wc.variant == "base" else STEPS
    return [f"{RESULTS}/seed_{wc.seed}/{wc.variant}/eval/step_{s:02d}.json" for s in steps]


SWEEP_PARAMS = {"seqlen": "frames", "posenoise": "pose_noise_mm_deg", "depthnoise": "depth_noise_mm"}


def report_sweeps(wc):
    """Sweep CSVs shown in the report; none unless config report_sweeps is true."""
    if not config.get("report_sweeps", False):
        return {}
    return {k: f"{RESULTS}/sweeps/{k}.csv" for k in SWEEPS if SWEEPS[k]}


RC = config["render"]


# The change-aware network's row (rules in change_aware.smk).
def change_aware_base_checkpoint():
    """config depth.change_aware_checkpoint; "default" = the one shipped with the package."""
    ck = DC.get("change_aware_checkpoint", "default")
    if ck == "default":
        from chisel.depth.change_aware import DEFAULT_CHANGE_CHECKPOINT

        return str(DEFAULT_CHANGE_CHECKPOINT)
    return ck


def change_aware_checkpoint(wc):
    if DC.get("finetune", True):
        return f"{RESULTS}/seed_{wc.seed}/depth/change_aware_finetuned.pt"
    return change_aware_base_checkpoint()


def change_aware_previous(wc):
    step = int(wc.step)
    if step == 1:
        return f"{RESULTS}/seed_{wc.seed}/preop/model.npz"
    return f"{RESULTS}/seed_{wc.seed}/base/change_aware/step_{step - 1:02d}/model.npz"


def extra_depth_inputs(wc):
    """The rendered sequence, and the estimator's TorchScript file when it has one."""
    inputs = {"index": f"{RESULTS}/seed_{wc.seed}/render/render.json"}
    if "torchscript" in EXTRA_DEPTH[wc.extra]:
        inputs["torchscript"] = EXTRA_DEPTH[wc.extra]["torchscript"]
    return inputs


def extra_depth_options(wc, input):
    spec = EXTRA_DEPTH[wc.extra]
    if "torchscript" in spec:
        opts = ["--torchscript", str(input.torchscript)]
    else:
        opts = ["--command", spec["command"]]
    if spec.get("metric", False):
        opts.append("--metric")
    return " ".join(shlex.quote(o) for o in opts)


# The `dataset` target (rules in dataset.smk): config dataset, options passed to
# `python -m sim dataset` only when set, so that sim keeps the one home of its defaults.
DATASET = dict(config.get("dataset") or {})
DATASET_DIR = f"{RESULTS}/dataset"


def dataset_seeds():
    from sim.dataset import parse_seeds

    if "seeds" not in DATASET:
        raise ValueError("config dataset.seeds: the `dataset` target needs seeds, e.g. '1000-1099'")
    return parse_seeds(DATASET["seeds"])


def dataset_options(wc=None):
    opts = []
    for key in ("bites", "frames", "preop_frames", "width", "height", "spp", "seed", "config"):
        if key in DATASET:
            opts += [f"--{key.replace('_', '-')}", str(DATASET[key])]
    for key in ("tools", "depth_only"):
        if DATASET.get(key, False):
            opts.append(f"--{key.replace('_', '-')}")
    return " ".join(shlex.quote(o) for o in opts)


def dataset_renders(wc):
    return [f"{DATASET_DIR}/seed_{s}" for s in dataset_seeds()]
