"""``python -m phantoms``: generate nasal-sinus phantoms, repair user surfaces.

Subcommands: ``generate`` (a phantom folder), ``repair`` (close a non-manifold surface),
``params`` (list the shape parameters and their ranges). Errors of the input print one
line naming the argument and exit with status 1.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from chisel.io.manifest import read_json_value
from phantoms.errors import ParameterRangeError, PhantomError

_DESCRIPTION = """\
Procedural nasal-sinus phantoms for Endoscopic Chisel.

Units: millimetres, mm^3 and Hounsfield units throughout. World frame: +x lateral
(towards the maxillary sinus), +y posterior (nostril -> choana), +z superior.
"""

_GENERATE_EPILOG = """\
Outputs in OUT (written to a temporary folder beside it, then renamed; an existing OUT
is replaced only when everything succeeded):
  phantom.json                  manifest: seed, shape parameters, steps, ROI box,
                                target lamella, airway path, CT description
  meshes/step_NN.ply            tissue solid after step NN (closed manifold, mm)
  meshes/step_NN_cut_faces.npy  uint8 per face of step_NN.ply: 1 = a face a cut created
  meshes/cutter_NN.ply          the cutter of step NN (mm; ragged for the procedures)
  ct/step_NN_label.nii.gz       label map, uint8: 0 air, 1 soft tissue, 2 bone
  ct/step_NN_hu.nii.gz          Hounsfield-like volume, int16: air -1000, soft tissue
                                40, bone 700, partial volume at surfaces (the
                                -480 HU iso-surface is the tissue surface)
  tet/step_NN.vtu               tetrahedral mesh (only with --tet; slow, ~20-60 s/step)
The NIfTI affine maps voxel indices to voxel centres in the world frame (mm).
See docs/phantoms.md for the manifest contract.
"""


def _param(text: str) -> tuple[str, float]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    name, value = text.split("=", 1)
    try:
        return name.strip(), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a number after {name}=, got {value!r}"
        ) from None


def _add_generate_parser(sub: argparse._SubParsersAction) -> None:
    """The ``generate`` subcommand and its options."""
    gen = sub.add_parser(
        "generate",
        help="generate a phantom: meshes, CT volumes and a manifest per surgical step",
        description="Generate a seeded nasal-sinus phantom and the steps of a surgical procedure: "
        "uncinectomy (default; 1-8 steps, default 5), ethmoidectomy (uncinectomy, then the ethmoid "
        "bulla's anterior wall and the walls between anterior ethmoid cells; 4-12 steps) or bites "
        "(small overlapping forceps bites on --target, the fine-change regime; 1-20 steps).",
        epilog=_GENERATE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    gen.add_argument("--seed", type=int, default=0, help="seed of every random choice (default 0)")
    gen.add_argument(
        "--seeds",
        help="generate several phantoms in one run (one start-up for all), e.g. 0-3 or 1,4,9: "
        "--out must hold {seed}, replaced by each seed; 'phantom written to DIR' is printed "
        "on stderr as each folder is complete",
    )
    gen.add_argument(
        "--bites",
        type=int,
        default=5,
        help="number of surgical steps (fragments or bites; default 5): uncinectomy 1-8, "
        "ethmoidectomy 4-12, bites 1-20",
    )
    gen.add_argument(
        "--procedure",
        default="uncinectomy",
        help="uncinectomy (default), ethmoidectomy or bites; see docs/phantoms.md",
    )
    gen.add_argument(
        "--out",
        type=Path,
        required=True,
        help="output folder (replaced atomically); with --seeds a pattern holding {seed}",
    )
    gen.add_argument(
        "--target",
        default="uncinate",
        help="lamella the bites perforate: uncinate (default), bulla or basal_lamella",
    )
    gen.add_argument(
        "--spacing-mm",
        type=float,
        default=0.5,
        help="CT voxel spacing in mm, 0.2-2.0 (default 0.5)",
    )
    gen.add_argument(
        "--noise-hu", type=float, default=0.0, help="std. dev. of seeded CT noise in HU (default 0)"
    )
    gen.add_argument(
        "--mucosa-mm",
        type=float,
        default=1.0,
        help="soft-tissue layer over bone in the CT, mm (default 1)",
    )
    gen.add_argument(
        "--roi-margin-mm",
        type=float,
        default=3.0,
        help="margin of the change ROI box, mm (default 3)",
    )
    gen.add_argument(
        "--mesh-edge-mm",
        type=float,
        default=0.5,
        help="surface edge length in mm, 0.3-2 (default 0.5; coarser is faster)",
    )
    gen.add_argument(
        "--bite-size-mm",
        type=float,
        nargs=2,
        default=(2.0, 5.0),
        metavar=("MIN", "MAX"),
        help="cutter jaw sizes, mm",
    )
    gen.add_argument(
        "--no-ct",
        dest="ct",
        action="store_false",
        help="write the meshes and phantom.json only, no CT volumes (all that rendering "
        "needs, in about half the time; phantom.json's ct is null, its steps have no ct_label "
        "or ct_hu)",
    )
    gen.add_argument(
        "--tet",
        action="store_true",
        help="also export a tetrahedral mesh per step (pytetwild; slow)",
    )
    gen.add_argument(
        "--tet-edge-mm", type=float, default=3.0, help="tetrahedron edge length, mm (default 3)"
    )
    gen.add_argument(
        "--param",
        type=_param,
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="fix a shape parameter (repeatable); `python -m phantoms params` lists names and ranges",
    )
    gen.add_argument(
        "--plan",
        type=Path,
        help="JSON list of steps to use instead of the planned ones: each a bite (center_mm, size_mm, "
        'R_world_from_cutter, shape) or {"bites": [bite, ...]} (one fragment of several bites); '
        "checked against --procedure's structures",
    )
    gen.set_defaults(func=_cmd_generate)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m phantoms",
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    _add_generate_parser(sub)

    rep = sub.add_parser(
        "repair",
        help="close a surface that is not a closed manifold (pytetwild), so it can be cut",
        description="Repair a triangle surface (holes, flipped or duplicated faces) into a closed 2-manifold. "
        "Reads any format trimesh reads (PLY, STL, OBJ, ...), writes PLY (mm).",
    )
    rep.add_argument("input", type=Path, help="input surface")
    rep.add_argument("output", type=Path, help="output PLY (written atomically)")
    rep.add_argument(
        "--edge-mm",
        type=float,
        help="tet edge length for the repair (default: 1/40 of the diagonal)",
    )
    rep.set_defaults(func=_cmd_repair)

    par = sub.add_parser("params", help="list the shape parameters with their ranges")
    par.set_defaults(func=_cmd_params)
    return parser


def _load_bite(b, where: str):
    from phantoms.bites import Bite

    try:
        return Bite(
            center_mm=tuple(b["center_mm"]),
            size_mm=tuple(b["size_mm"]),
            R_world_from_cutter=tuple(
                tuple(r) for r in b.get("R_world_from_cutter", [[1, 0, 0], [0, 1, 0], [0, 0, 1]])
            ),
            shape=b.get("shape", "ellipsoid"),
        )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ParameterRangeError(
            where, f"expected center_mm and size_mm lists of numbers: {exc}"
        ) from None


def _load_plan(path: Path):
    """Plan entries: a bite object, or {"bites": [...]} / a list of bites (one fragment)."""
    raw = read_json_value(path, ParameterRangeError)
    if not isinstance(raw, list) or not raw:
        raise ParameterRangeError(path, "expected a non-empty JSON list of bites")
    steps = []
    for i, entry in enumerate(raw):
        where = f"{path} bite {i}"
        group = entry.get("bites") if isinstance(entry, dict) and "bites" in entry else entry
        if isinstance(group, list):
            if not group:
                raise ParameterRangeError(where, "expected at least one bite in the fragment")
            steps.append([_load_bite(b, f"{where}.{j}") for j, b in enumerate(group)])
        else:
            steps.append(_load_bite(entry, where))
    return steps


def _seeds_and_outs(args: argparse.Namespace) -> list[tuple[int, Path]]:
    """(seed, output folder) of each phantom to generate: ``--seed``, or every seed of
    ``--seeds`` with ``{seed}`` in ``--out`` replaced."""
    from chisel.core.config import seed_list  # noqa: PLC0415

    if args.seeds is None:
        return [(args.seed, args.out)]
    try:
        seeds = seed_list(args.seeds)
    except ValueError as exc:
        raise ParameterRangeError("--seeds", str(exc)) from None
    if "{seed}" not in str(args.out):
        raise ParameterRangeError(
            "--out", f"with --seeds the output must hold {{seed}}, got {str(args.out)!r}"
        )
    return [(s, Path(str(args.out).replace("{seed}", str(s)))) for s in seeds]


def _cmd_generate(args: argparse.Namespace) -> int:
    from phantoms.generate import generate
    from phantoms.io import check_output_dir
    from phantoms.params import PhantomConfig
    from phantoms.procedures import PROCEDURES, STEP_RANGES

    bites = _load_plan(args.plan) if args.plan else None
    if bites and args.procedure in PROCEDURES:
        lo, hi = STEP_RANGES[args.procedure]
        if not lo <= len(bites) <= hi:
            raise ParameterRangeError(
                f"--plan {args.plan}",
                f"{len(bites)} steps; procedure {args.procedure} takes {lo}-{hi}",
            )
    # every config and output folder is checked before the first phantom is built
    runs = []
    for seed, out in _seeds_and_outs(args):
        cfg = PhantomConfig(
            seed=seed,
            procedure=args.procedure,
            n_bites=len(bites) if bites else args.bites,
            target=args.target,
            bite_size_mm=tuple(args.bite_size_mm),
            spacing_mm=args.spacing_mm,
            noise_hu=args.noise_hu,
            mucosa_mm=args.mucosa_mm,
            roi_margin_mm=args.roi_margin_mm,
            mesh_edge_mm=args.mesh_edge_mm,
            ct=args.ct,
            tet=args.tet,
            tet_edge_mm=args.tet_edge_mm,
            overrides=dict(args.param),
        )
        check_output_dir(out)
        runs.append((cfg, out))
    for cfg, out in runs:
        written = generate(
            cfg, out, bites=bites, show_progress=True, plan_source=f"{args.plan} bite"
        )
        # sim dataset waits for this line (one per seed) to render a phantom while the
        # next one is generated
        sys.stderr.write(f"phantom written to {written}\n")
        sys.stderr.flush()
    return 0


def _cmd_repair(args: argparse.Namespace) -> int:
    import numpy as np

    from chisel.core.atomic import check_writable_parent
    from chisel.core.errors import InvalidInputError
    from chisel.io.meshfile import READABLE_MESH_SUFFIXES, read_mesh_file
    from phantoms.errors import NotManifoldError, OutputError
    from phantoms.io import atomic_write_bytes, ply_bytes
    from phantoms.tet import repair_surface

    # A file output: an existing file is replaced (atomically, once the repair succeeded);
    # a folder is refused before the (slow) repair, as is a parent that cannot be written.
    out = Path(args.output)
    if out.is_dir():
        raise OutputError(f"output {out}", "is a folder; expected the path of a PLY file to write")
    try:
        check_writable_parent(out)
    except InvalidInputError as exc:
        raise OutputError(f"output {out}", exc.problem) from None
    mesh = read_mesh_file(args.input, "surface", READABLE_MESH_SUFFIXES, error=NotManifoldError)
    v, f = repair_surface(np.asarray(mesh.vertices), np.asarray(mesh.faces), edge_mm=args.edge_mm)
    atomic_write_bytes(out, ply_bytes(v, f))  # an OSError: OutputError naming the file
    sys.stderr.write(f"repaired surface ({len(f)} triangles) written to {args.output}\n")
    return 0


def _cmd_params(args: argparse.Namespace) -> int:
    from phantoms.params import PARAM_RANGES

    for name, (lo, hi, doc) in PARAM_RANGES.items():
        sys.stdout.write(f"{name:32s} [{lo:g}, {hi:g}]  {doc}\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 0 if args.command is None else 2
    try:
        return int(args.func(args) or 0)
    except PhantomError as exc:
        sys.stderr.write(f"phantoms {args.command}: error: {exc}\n")
        return 1
