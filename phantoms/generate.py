"""The phantom pipeline: anatomy -> bites -> CT volumes (+ tets) -> an output folder.

:func:`build_phantom` is the pure stage (configuration in, :class:`Phantom` in memory
out); :func:`write_phantom` is the thin I/O wrapper that writes the folder atomically;
:func:`generate` does both. The folder layout and the manifest ``phantom.json`` are
documented in ``docs/phantoms.md``.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import manifold3d as m3d
import numpy as np

from phantoms.anatomy import Anatomy, arrays_from_manifold, build_anatomy
from phantoms.bites import Bite, Target, find_target
from phantoms.ct import (
    HU_AIR,
    HU_BONE,
    HU_SOFT_TISSUE,
    ISO_HU,
    LABEL_AIR,
    LABEL_BONE,
    LABEL_SOFT_TISSUE,
    CTGrid,
    SurfaceDistance,
    clip_distance_mm,
    ct_noise,
    grid_for_block,
    hu_from_sd,
    labels_from_sd,
    nifti_gz_bytes,
    update_sd,
)
from phantoms.errors import AnatomyError
from phantoms.io import (
    atomic_dir,
    atomic_write_bytes,
    check_output_dir,
    json_bytes,
    npy_bytes,
    ply_bytes,
    rounded,
)
from phantoms.params import PARAM_RANGES, PhantomConfig, sample_params
from phantoms.path import airway_path
from phantoms.procedures import (
    Fragment,
    StepCut,
    cut_steps,
    plan_allowed_region,
    plan_procedure,
)
from phantoms.regime import REGIME_WINDOWS, view_change_mm
from phantoms.roi import change_box

log = logging.getLogger(__name__)

MAX_ANATOMY_DRAWS = 16
"""Parameter draws a seed gets for an anatomy whose airway takes the endoscope to the
target (4 of seeds 0-129 need a second for that alone: 25, 56, 83 and 126) and, with a
procedure that has a :data:`~phantoms.regime.REGIME_WINDOWS` entry, whose surgery is
specimen-sized."""

FORMAT = "endoscopic-chisel/phantom"
VERSION = 1
WORLD_FRAME = (
    "mm; +x lateral (towards the maxillary sinus), +y posterior (nostril -> choana), +z superior; "
    "one nasal side (the patient's left: the frame is DICOM LPS), septum midline face at x = -3.5, "
    "nostril on the plane y = 0, nasal floor near z = 0"
)


@dataclass(frozen=True)
class Step:
    """One surgical step: the tissue solid and its CT volumes."""

    name: str
    vertices_mm: np.ndarray
    """(V, 3) float64, mm."""
    faces: np.ndarray
    """(F, 3) int64, counter-clockwise seen from outside the tissue."""
    volume_mm3: float
    removed_volume_mm3: float
    label: np.ndarray | None
    """(nx, ny, nz) uint8: 0 air, 1 soft tissue, 2 bone; None without CT (``config.ct``)."""
    hu: np.ndarray | None
    """(nx, ny, nz) int16 Hounsfield-like units; None without CT."""
    cutter_vertices_mm: np.ndarray | None = None
    cutter_faces: np.ndarray | None = None
    cut_faces: np.ndarray | None = None
    """(F,) bool: True where the face was created by a cutter of this or an earlier step."""
    fragment: Fragment | None = None
    """The step's fragment (None for the preoperative step)."""
    tet_points_mm: np.ndarray | None = None
    """(P, 3) float64, mm; only with ``config.tet``."""
    tets: np.ndarray | None = None
    """(T, 4) int, VTK ordering (positive volume)."""


@dataclass(frozen=True)
class Phantom:
    """A generated phantom in memory (everything the folder holds)."""

    config: PhantomConfig
    params: dict
    anatomy: Anatomy
    target: Target
    bites: tuple[Bite, ...]
    """The first bite of each step (for a procedure's ragged fragments: empty)."""
    steps: tuple[Step, ...]
    grid: CTGrid
    roi_min_mm: np.ndarray
    roi_max_mm: np.ndarray
    airway_path_mm: np.ndarray
    """(N, 3) float64, mm."""
    anatomy_draw: int = 0
    """Which of the seed's parameter draws this anatomy is (:data:`MAX_ANATOMY_DRAWS`)."""
    view_change_mm: tuple[float, ...] = ()
    """Per step, how far the surgery moves the surface the endoscope sees in the change box
    (:func:`phantoms.regime.view_change_mm`), mm."""
    regime_met: bool | None = None
    """Whether that is inside the procedure's :data:`~phantoms.regime.REGIME_WINDOWS`
    window (None: the procedure has none, or the plan was given)."""


def _plan_fragment(entry, target: str) -> Fragment:
    """A plan entry (one :class:`Bite` or a sequence of bites = one fragment) as a step."""
    if isinstance(entry, Fragment):
        return entry
    if isinstance(entry, Bite):
        return Fragment("bites", target, {}, (entry,))
    return Fragment("bites", target, {"n_bites": len(entry)}, tuple(entry))


def build_phantom(
    config: PhantomConfig,
    bites: list | None = None,
    progress: Callable[[str], None] | None = None,
    plan_source: str = "plan bite",
) -> Phantom:
    """Generate the anatomy, apply the bite plan, and voxelise every step.

    Parameters
    ----------
    config : PhantomConfig
    bites : list, optional
        An explicit surgical plan, one entry per step: a :class:`Bite`, or a list of bites
        taken together as one fragment. It is checked against ``config.procedure``'s
        structures (errors name ``"<plan_source> entry i"``). By default the procedure
        (:func:`phantoms.procedures.plan_procedure`) plans ``config.n_bites`` steps.
    progress : callable, optional
        Called with a short message as each stage finishes.

    Raises
    ------
    ProcedureError, UnknownTargetError, AnatomyError, ParameterRangeError
    """
    note = progress or (lambda _msg: None)
    d = _draw_anatomy(config, bites, plan_source, note)
    # an explicit plan is a list of bites, whatever the procedure
    step_name = "bite" if config.procedure == "bites" or bites is not None else "fragment"
    grid, steps = _voxelise_steps(config, d.anatomy, d.fragments, d.results, step_name, note)
    return Phantom(
        config=config,
        params=d.params,
        anatomy=d.anatomy,
        target=d.target,
        bites=tuple(f.bites[0] for f in d.fragments if f.bites),
        steps=tuple(steps),
        grid=grid,
        roi_min_mm=d.box_mm[0],
        roi_max_mm=d.box_mm[1],
        airway_path_mm=d.path,
        anatomy_draw=d.draw,
        view_change_mm=tuple(d.view_change_mm),
        regime_met=d.regime_met,
    )


def draw_seed(seed: int, draw: int) -> int:
    """The seed that a draw's anatomy and plan use: the phantom seed itself for draw 0 (so a
    seed's first draw is what it always was), an independent 31-bit seed for later ones."""
    if draw == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), 0xD5A, int(draw)]).generate_state(1)[0] >> 1)


@dataclass(frozen=True)
class _Draw:
    """One anatomy draw with its plan, airway path, change box and view of the change."""

    draw: int
    params: dict
    anatomy: Anatomy
    target: Target
    fragments: list[Fragment]
    results: list[StepCut]
    path: np.ndarray
    box_mm: tuple[np.ndarray, np.ndarray]
    view_change_mm: list[float]
    regime_met: bool | None


def _draw_anatomy(
    config: PhantomConfig, bites: list | None, plan_source: str, note: Callable[[str], None]
) -> _Draw:
    """The seed's anatomy, its plan, airway path and change box.

    An anatomy the generator cannot use is drawn again from the seed's next stream
    (``sample_params(seed, draw=k)``; draw 0 is the seed's first), at most
    :data:`MAX_ANATOMY_DRAWS` times, with the procedure's own plan only (an explicit plan
    was made for one anatomy and keeps it): one whose airway is too narrow for the
    endoscope to reach the target (an error when no draw has one), and, for a procedure
    with a :data:`~phantoms.regime.REGIME_WINDOWS` entry, one whose surgery looks smaller
    or larger to the endoscope than the specimen's (when no draw is inside the window, the
    draw nearest to it, with ``regime_met`` False and a warning).
    """
    draws = MAX_ANATOMY_DRAWS if bites is None else 1
    window = REGIME_WINDOWS.get(config.procedure) if bites is None else None
    best: _Draw | None = None
    airway_error: AnatomyError | None = None
    for draw in range(draws):
        params = sample_params(config.seed, config.overrides, draw=draw)
        # A later draw is a new anatomy throughout: its airway undulation, ethmoid cells
        # and the procedure's plan come from streams of their own too (shape parameters
        # alone left most of a seed's draws alike: seeds needed up to 11 to fit the window).
        stream = draw_seed(config.seed, draw)
        anatomy = build_anatomy(params, stream, config.mesh_edge_mm)
        note("anatomy")
        target, fragments, results = _cut_plan(
            anatomy, replace(config, seed=stream), bites, plan_source
        )
        note("bites")
        try:
            path = airway_path(
                SurfaceDistance(*arrays_from_manifold(anatomy.tissue)),
                np.asarray(anatomy.nostril_mm),
                np.asarray(anatomy.airway_min_mm),
                np.asarray(anatomy.airway_max_mm),
                target,
            )
        except AnatomyError as exc:
            if draws == 1:
                raise
            airway_error = exc
            log.info("seed %d, anatomy draw %d: %s; drawing again", config.seed, draw, exc)
            continue
        note("airway path")
        center, normal = np.asarray(target.center_mm), np.asarray(target.normal)
        lo, hi, _ = change_box(
            anatomy.tissue, results[-1].tissue, path[-1], center, normal, config.roi_margin_mm
        )
        note("change box")
        view = view_change_mm(
            anatomy.tissue, [r.tissue for r in results], (lo, hi), path[-1], center, normal
        )
        miss = window.miss(view) if window is not None else ""
        d = _Draw(
            draw, params, anatomy, target, fragments, results, path, (lo, hi), view,
            None if window is None else not miss,
        )  # fmt: skip
        if not miss:
            return d
        assert window is not None
        log.info(
            "seed %d, anatomy draw %d: the surgery's view %s; drawing again",
            config.seed,
            draw,
            miss,
        )
        if best is None or window.distance(view) < window.distance(best.view_change_mm):
            best = d
    if best is None:
        assert airway_error is not None
        raise AnatomyError(
            airway_error.source,
            f"{airway_error.problem} (seed {config.seed}: none of {draws} anatomy draws has one)",
        )
    log.warning(
        "seed %d: none of %d anatomy draws gives a specimen-sized %s (view of the change %s "
        "mm); keeping draw %d, the nearest", config.seed, draws, config.procedure,
        [round(v, 2) for v in best.view_change_mm], best.draw,
    )  # fmt: skip
    return best


def _cut_plan(
    anatomy: Anatomy, config: PhantomConfig, bites: list | None, plan_source: str
) -> tuple[Target, list[Fragment], list[StepCut]]:
    """The target, one fragment per step and the cuts applied: the procedure's own plan,
    or the explicit ``bites`` checked against the procedure's structures."""
    if bites is None:
        return plan_procedure(
            anatomy,
            config.procedure,
            config.n_bites,
            config.seed,
            config.target,
            config.bite_size_mm,
        )
    target, _, _ = find_target(anatomy, config.target)
    fragments = [_plan_fragment(b, config.target) for b in bites]
    results = cut_steps(
        anatomy,
        fragments,
        config.procedure,
        allowed=plan_allowed_region(anatomy, config.procedure, config.target),
        where=f"{plan_source} {{i}}",
        edge_mm=min(config.mesh_edge_mm, 0.3),
    )
    return target, fragments, results


def _voxelise_steps(
    config: PhantomConfig,
    anatomy: Anatomy,
    fragments: list[Fragment],
    results: list[StepCut],
    step_name: str,
    note: Callable[[str], None],
) -> tuple[CTGrid, list[Step]]:
    """The CT grid and every step's surface and volumes (step 0 = preop).

    The signed distance is computed once on the whole grid for the preop surface, then
    updated inside each cutter's box only; not at all without CT (``config.ct``)."""
    clip = clip_distance_mm(config.spacing_mm, config.mucosa_mm)
    grid = grid_for_block(
        anatomy.block_min_mm,
        anatomy.block_max_mm,
        config.spacing_mm,
        clip[0] + 2 * config.spacing_mm,
    )
    noise = ct_noise(grid.shape, config.noise_hu, config.seed) if config.ct else None
    steps: list[Step] = []
    sd: np.ndarray | None = None
    for k, cut in enumerate([None, *results]):
        solid = anatomy.tissue if cut is None else cut.tissue
        v, f = arrays_from_manifold(solid)
        surface = SurfaceDistance(v, f)
        if cut is None:
            if config.ct:
                sd = surface.signed_distance_grid(grid.points(), clip, grid.spacing_mm)
        elif sd is not None:  # with CT; step 0 (preop) came first
            box = cut.cutter.bounding_box()
            sd = update_sd(sd, grid, surface, np.asarray(box[:3]), np.asarray(box[3:]), clip)
        name = "preop" if cut is None else f"{step_name}_{k}"
        fragment = None if cut is None else fragments[k - 1]
        steps.append(_step(config, name, solid, v, f, sd, noise, cut, fragment))
        note(f"step {k} volumes")
    return grid, steps


def _step(
    config: PhantomConfig,
    name: str,
    solid: m3d.Manifold,
    v: np.ndarray,
    f: np.ndarray,
    sd: np.ndarray | None,
    noise: np.ndarray | None,
    cut: StepCut | None,
    fragment: Fragment | None,
) -> Step:
    """One step from its surface ``v, f`` (of ``solid``) and the grid's signed distance
    ``sd`` to it (None: no CT); ``cut`` and ``fragment`` are None for the preoperative
    step."""
    cv = cf = None
    if cut is not None:
        cv, cf = arrays_from_manifold(cut.cutter)
    tet_pts = tets = None
    if config.tet:
        from phantoms.tet import tetrahedralize

        tet_pts, tets = tetrahedralize(v, f, config.tet_edge_mm)
    return Step(
        name=name,
        vertices_mm=v,
        faces=f,
        volume_mm3=float(solid.volume()),
        removed_volume_mm3=0.0 if cut is None else float(cut.removed_volume_mm3),
        label=None if sd is None else labels_from_sd(sd, config.mucosa_mm),
        hu=None if sd is None else hu_from_sd(sd, config.spacing_mm, config.mucosa_mm, noise),
        cutter_vertices_mm=cv,
        cutter_faces=cf,
        cut_faces=np.zeros(len(f), bool) if cut is None else cut.cut_faces,
        fragment=fragment,
        tet_points_mm=tet_pts,
        tets=tets,
    )


def manifest(ph: Phantom) -> dict:
    """The ``phantom.json`` contract (paths relative to the output folder)."""
    steps = []
    for k, st in enumerate(ph.steps):
        entry: dict = {"step": k, "name": st.name, "mesh": f"meshes/step_{k:02d}.ply"}
        if st.cutter_vertices_mm is not None:
            entry["cutter_mesh"] = f"meshes/cutter_{k:02d}.ply"
        if st.label is not None:
            entry["ct_label"] = f"ct/step_{k:02d}_label.nii.gz"
            entry["ct_hu"] = f"ct/step_{k:02d}_hu.nii.gz"
        if st.tets is not None:
            entry["tet_mesh"] = f"tet/step_{k:02d}.vtu"
        entry["cut_faces"] = f"meshes/step_{k:02d}_cut_faces.npy"
        entry["cut_face_count"] = int(st.cut_faces.sum()) if st.cut_faces is not None else 0
        entry["volume_mm3"] = st.volume_mm3
        entry["removed_volume_mm3"] = st.removed_volume_mm3
        if st.fragment is not None:
            entry["structure"] = st.fragment.params.get("structure_label", st.fragment.structure)
            if st.fragment.bites:
                entry["bite"] = st.fragment.bites[0].to_dict()
            entry["fragment"] = st.fragment.to_dict()
        steps.append(entry)
    a = ph.anatomy
    cfg = asdict(ph.config)
    cfg["bite_size_mm"] = list(cfg["bite_size_mm"])
    params = dict(ph.params)
    params["ethmoid_cells_mm"] = [
        {
            "name": c.name,
            "center_mm": list(c.center_mm),
            "radius_mm": c.radius_mm,
            "wall_mm": c.wall_mm,
        }
        for c in a.cells
    ]
    params["maxillary_sinus"] = {
        "center_mm": list(a.maxillary_center_mm),
        "semi_axes_mm": list(a.maxillary_semi_axes_mm),
        "volume_mm3": a.maxillary_volume_mm3,
    }
    params["block_mm"] = [list(a.block_min_mm), list(a.block_max_mm)]
    params["nostril_mm"] = list(a.nostril_mm)
    return rounded(
        {
            "format": FORMAT,
            "version": VERSION,
            "seed": ph.config.seed,
            "anatomy_draw": ph.anatomy_draw,
            "procedure": ph.config.procedure,
            # how large the surgery looks to the endoscope, and whether the draw is
            # specimen-sized (phantoms.regime; null: the procedure has no window)
            "view_change_mm": [None if v != v else v for v in ph.view_change_mm],
            "regime_met": ph.regime_met,
            "params": params,
            "param_ranges": {k: [lo, hi] for k, (lo, hi, _) in PARAM_RANGES.items()},
            "world_frame": WORLD_FRAME,
            "steps": steps,
            "roi_box_mm": [list(ph.roi_min_mm), list(ph.roi_max_mm)],
            "target": {
                "name": ph.target.name,
                "center_mm": list(ph.target.center_mm),
                "normal": list(ph.target.normal),
                "thickness_mm": ph.target.thickness_mm,
            },
            "airway_path_mm": ph.airway_path_mm.tolist(),
            # without CT volumes (config.ct False) the block is null: no grid to describe
            "ct": None
            if not ph.config.ct
            else {
                "spacing_mm": ph.grid.spacing_mm,
                "shape": list(ph.grid.shape),
                "T_world_from_voxel": ph.grid.T_world_from_voxel.tolist(),
                "labels": {"air": LABEL_AIR, "soft_tissue": LABEL_SOFT_TISSUE, "bone": LABEL_BONE},
                "hu": {"air": HU_AIR, "soft_tissue": HU_SOFT_TISSUE, "bone": HU_BONE},
                "iso_hu": ISO_HU,
                "mucosa_mm": ph.config.mucosa_mm,
                "noise_hu": ph.config.noise_hu,
            },
            "config": cfg,
        }
    )


def write_phantom(
    ph: Phantom, out_dir: str | Path, progress: Callable[[str], None] | None = None
) -> Path:
    """Write the phantom folder atomically (see ``docs/phantoms.md`` for the layout)."""
    note = progress or (lambda _msg: None)
    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as tmp:
        T = ph.grid.T_world_from_voxel
        for k, st in enumerate(ph.steps):
            atomic_write_bytes(
                tmp / f"meshes/step_{k:02d}.ply", ply_bytes(st.vertices_mm, st.faces)
            )
            atomic_write_bytes(
                tmp / f"meshes/step_{k:02d}_cut_faces.npy",
                npy_bytes(
                    (
                        np.zeros(len(st.faces), bool) if st.cut_faces is None else st.cut_faces
                    ).astype(np.uint8)
                ),
            )
            if st.cutter_vertices_mm is not None:
                assert st.cutter_faces is not None  # set together (arrays_from_manifold)
                atomic_write_bytes(
                    tmp / f"meshes/cutter_{k:02d}.ply",
                    ply_bytes(st.cutter_vertices_mm, st.cutter_faces),
                )
            if st.label is not None and st.hu is not None:
                atomic_write_bytes(
                    tmp / f"ct/step_{k:02d}_label.nii.gz",
                    nifti_gz_bytes(st.label, T, "label 0 air 1 soft 2 bone"),
                )
                atomic_write_bytes(
                    tmp / f"ct/step_{k:02d}_hu.nii.gz",
                    nifti_gz_bytes(st.hu, T, "Hounsfield-like units"),
                )
            if st.tets is not None:
                from phantoms.tet import vtu_bytes

                assert st.tet_points_mm is not None  # set together (tetrahedralize)
                atomic_write_bytes(
                    tmp / f"tet/step_{k:02d}.vtu", vtu_bytes(st.tet_points_mm, st.tets)
                )
            note(f"wrote step {k}")
        atomic_write_bytes(tmp / "phantom.json", json_bytes(manifest(ph)))
    return out_dir


def generate(
    config: PhantomConfig,
    out_dir: str | Path,
    bites: list | None = None,
    show_progress: bool = False,
    plan_source: str = "plan bite",
) -> Path:
    """Build a phantom and write it to ``out_dir`` (replaced only on success).

    The output folder is checked before any work, so an unwritable one fails fast with
    :class:`~phantoms.errors.OutputError`.
    """
    check_output_dir(out_dir)
    total = 4 + 2 * ((config.n_bites if bites is None else len(bites)) + 1)
    bar = None
    if show_progress:
        from tqdm import tqdm

        bar = tqdm(total=total, desc="phantom", unit="stage", file=sys.stderr, leave=False)

    def note(msg: str) -> None:
        log.debug(msg)
        if bar is not None:
            bar.set_postfix_str(msg, refresh=False)
            bar.update(1)

    try:
        ph = build_phantom(config, bites, note, plan_source)
        return write_phantom(ph, out_dir, note)
    finally:
        if bar is not None:
            bar.close()
