"""``chisel evaluate`` (one step, tables, seeds, sweeps) and ``chisel report``."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from chisel.cli.args import Output, finite_float
from chisel.core.errors import InvalidInputError
from chisel.eval.metrics import (
    RoiBox,
)
from chisel.eval.step import (
    evaluate_step,
    load_mesh,
)
from chisel.eval.surface import (
    SurfaceMetricConfig,
)
from chisel.eval.tables import (
    aggregate_seeds,
    assemble_table,
    read_metrics,
    read_step_metrics,
    read_sweep_csv,
    tabulate_sweep,
    write_seed_table,
    write_step_metrics,
    write_sweep_csv,
    write_table,
)

log = logging.getLogger(__name__)

_EVALUATE_HELP = """\
Evaluate the methods' meshes of one surgical step against its ground-truth mesh.

Correspondence error (the paper's metric): depth is rendered from the GT mesh and from
each method's mesh at the evaluation poses of --eval-sequence (its true poses when it has
them, else its tracked poses); same-pixel points are back-projected to world mm, and the
mean ± std distance over pixels whose GT point lies inside the ROI box (and where the
method has a surface) is reported, with the count and the missing fraction.
Surface metrics inside the box: accuracy, completeness, HD95, chamfer, F-score at 1 mm.
Change masks (optional): precision / recall against what each method's model lacked when
the step began (this step's GT surface > 1 mm beyond --start-surfaces' surface), along the
masks' own rays (the poses stored with them, else --change-sequence's tracked poses).

Subcommands: 'table' (step files -> metrics.json/.csv/.md), 'seeds' (several
metrics.json -> mean and spread), 'sweep' (metrics.json per swept value -> CSV).
Units: mm. See docs/evaluation.md.
"""


def _name_path_pairs(items: list[str] | None, option: str) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for item in items or []:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise InvalidInputError(option, f"expected NAME=PATH, got {item!r}")
        if name in out:
            raise InvalidInputError(option, f"{name!r} given twice")
        out[name] = Path(path)
    return out


def _run_step(args: argparse.Namespace) -> int:
    if args.seed < 0:
        raise InvalidInputError("--seed", f"must be >= 0, got {args.seed}")
    try:  # the bounds' one home is SurfaceMetricConfig; checked before anything is read
        cfg = SurfaceMetricConfig(n_samples=args.samples, seed=args.seed)
    except InvalidInputError as exc:
        raise InvalidInputError("--samples", exc.problem) from None
    missing = [
        opt
        for opt, val in (
            ("--gt-mesh", args.gt_mesh),
            ("--method", args.method),
            ("--eval-sequence", args.eval_sequence),
            ("--roi", args.roi),
            ("--step", args.step),
            ("--out", args.out),
        )
        if not val and val != 0
    ]
    if missing:
        raise InvalidInputError(
            "chisel evaluate", f"missing required option(s) {', '.join(missing)}"
        )
    result = evaluate_step(
        args.gt_mesh,
        _name_path_pairs(args.method, "--method"),
        args.eval_sequence,
        RoiBox.parse(args.roi),
        step=args.step,
        cfg=cfg,
        change_mask_paths=_name_path_pairs(args.change_masks, "--change-masks") or None,
        change_sequence_path=args.change_sequence,
        start_surface_paths=_name_path_pairs(args.start_surfaces, "--start-surfaces") or None,
    )
    write_step_metrics(args.out, result)
    log.info("wrote %s", args.out)
    return 0


def _run_table(args: argparse.Namespace) -> int:
    steps = [read_step_metrics(p) for p in args.inputs]
    paths = write_table(args.out_dir, assemble_table(steps, args.experiment))
    log.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return 0


def _run_seeds(args: argparse.Namespace) -> int:
    tables = [read_metrics(p) for p in args.inputs]
    labels = args.labels or [str(p) for p in args.inputs]
    paths = write_seed_table(args.out_dir, aggregate_seeds(tables, labels))
    log.info("wrote %s", ", ".join(str(p) for p in paths.values()))
    return 0


def _run_sweep(args: argparse.Namespace) -> int:
    runs = []
    for item in args.run:
        value, sep, path = item.partition("=")
        try:
            v = float(value)
        except ValueError:
            raise InvalidInputError("--run", f"expected VALUE=METRICS_JSON, got {item!r}") from None
        if not sep or not path:
            raise InvalidInputError("--run", f"expected VALUE=METRICS_JSON, got {item!r}")
        runs.append((v, read_metrics(path)))
    write_sweep_csv(args.out, tabulate_sweep(args.param, runs))
    log.info("wrote %s", args.out)
    return 0


def _run_report(args: argparse.Namespace) -> int:
    # Imported here: plotly is only needed for the report.
    from chisel.eval.ct_slices import read_ct_slices
    from chisel.eval.report import ReportMeshes, read_panels, write_report

    metrics = read_metrics(args.metrics)
    panels = read_panels(args.panels) if args.panels else None
    meshes = None
    if bool(args.preop_mesh) != bool(args.updated_mesh):
        raise InvalidInputError(
            "--preop-mesh/--updated-mesh", "give both meshes for the 3D view, or neither"
        )
    if args.preop_mesh:
        meshes = ReportMeshes(
            load_mesh(args.preop_mesh, "preoperative mesh"),
            load_mesh(args.updated_mesh, "updated mesh"),
            removed_threshold_mm=args.removed_threshold_mm,
            max_faces=args.max_faces,
            roi_box=RoiBox.parse(args.roi) if args.roi else None,
        )
    sweeps = {
        name: read_sweep_csv(p) for name, p in _name_path_pairs(args.sweep, "--sweep").items()
    }
    ct_slices = [s for p in args.ct_slices or [] for s in read_ct_slices(p)]
    write_report(
        args.out, metrics, panels, meshes, sweeps or None, title=args.title, ct_slices=ct_slices
    )
    log.info("wrote %s", args.out)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    fmt = argparse.RawDescriptionHelpFormatter
    p = subparsers.add_parser(
        "evaluate",
        help="score methods' meshes against ground truth; tabulate results",
        description=_EVALUATE_HELP,
        formatter_class=fmt,
    )
    p.add_argument("--gt-mesh", type=Path, help="ground-truth mesh of the step (PLY/STL/OBJ, mm)")
    p.add_argument(
        "--method",
        nargs="+",
        metavar="NAME=MESH",
        help="method name and its mesh, e.g. updated=model.ply no_update=preop.ply",
    )
    p.add_argument("--eval-sequence", type=Path, help="sequence folder with the evaluation poses")
    p.add_argument(
        "--roi",
        help="ROI box in world mm: 'xmin,ymin,zmin,xmax,ymax,zmax'; write --roi=-4,... "
        "when the first number is negative",
    )
    p.add_argument("--step", type=int, help="surgical step (0 = preop)")
    p.add_argument("--out", type=Path, help="output step_metrics.json", action=Output)
    p.add_argument(
        "--samples",
        type=int,
        default=50_000,
        help="surface samples per mesh in the box (100 to 10^7: memory grows with it)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the surface sampling")
    p.add_argument(
        "--change-masks",
        nargs="+",
        metavar="NAME=MASKS",
        help="predicted change masks per method (.npz with key 'masks', or a PNG folder)",
    )
    p.add_argument("--change-sequence", type=Path, help="the step's update sequence (mask poses)")
    p.add_argument(
        "--start-surfaces",
        nargs="+",
        metavar="NAME=MODEL",
        help="per method with masks, the model (.npz) or mesh its step began from: the masks "
        "are scored against what it lacked",
    )
    p.set_defaults(func=_run_step)
    sub = p.add_subparsers(dest="evaluate_command", metavar="SUBCOMMAND")

    t = sub.add_parser("table", help="combine step_metrics.json files into metrics.json/.csv/.md")
    t.add_argument("--inputs", nargs="+", type=Path, required=True, help="step_metrics.json files")
    t.add_argument("--out-dir", type=Path, required=True, help="folder for metrics.json/.csv/.md")
    t.add_argument("--experiment", default="default", help="experiment name stored in the table")
    t.set_defaults(func=_run_table)

    s = sub.add_parser("seeds", help="mean and spread of several metrics.json (one per seed)")
    s.add_argument("--inputs", nargs="+", type=Path, required=True, help="metrics.json files")
    s.add_argument("--labels", nargs="+", help="a label per input (default: the paths)")
    s.add_argument("--out-dir", type=Path, required=True, help="folder for metrics_seeds.*")
    s.set_defaults(func=_run_seeds)

    w = sub.add_parser("sweep", help="error against a swept parameter -> CSV")
    w.add_argument("--param", required=True, help="parameter name with unit, e.g. pose_noise_mm")
    w.add_argument(
        "--run", nargs="+", required=True, metavar="VALUE=METRICS_JSON", help="one per swept value"
    )
    w.add_argument("--out", type=Path, required=True, help="output CSV", action=Output)
    w.set_defaults(func=_run_sweep)

    r = subparsers.add_parser(
        "report",
        help="self-contained HTML report (tables, plots, panels, 3D view)",
        description="Write one offline HTML file: the metrics tables, error per step, sweep "
        "plots, per-step depth panels, axial and coronal slices of the preoperative and "
        "updated CTs through the change box (window W 2000 / L 0 HU, radiological "
        "orientation, removed region outlined, updated-CT Dice), and a 3D view of the "
        "preoperative and updated meshes.",
    )
    r.add_argument("--metrics", type=Path, required=True, help="metrics.json")
    r.add_argument("--panels", type=Path, help="panels .npz (chisel.eval.report.write_panels)")
    r.add_argument("--preop-mesh", type=Path, help="preoperative model mesh (3D view)")
    r.add_argument("--updated-mesh", type=Path, help="updated model mesh (3D view)")
    r.add_argument(
        "--roi", help="ROI box drawn in the 3D view: --roi=xmin,ymin,zmin,xmax,ymax,zmax (mm)"
    )
    r.add_argument(
        "--removed-threshold-mm", type=finite_float, default=0.5, help="highlight distance, mm"
    )
    r.add_argument(
        "--max-faces", type=int, default=60_000, help="triangles per mesh after decimation"
    )
    r.add_argument(
        "--sweep", nargs="+", metavar="NAME=CSV", help="sweep CSVs (chisel evaluate sweep)"
    )
    r.add_argument(
        "--ct-slices",
        nargs="+",
        type=Path,
        metavar="NPZ",
        help="updated-CT slices through the change box, one .npz per step "
        "(chisel.eval.ct_slices.write_ct_slices; the workflow's export/step_NN_slices.npz)",
    )
    r.add_argument("--title", default="Endoscopic Chisel: evaluation report")
    r.add_argument("--out", type=Path, required=True, help="output .html", action=Output)
    r.set_defaults(func=_run_report)
