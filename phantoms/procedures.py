"""Surgical procedures: FESS progressions as a sequence of ragged tissue fragments.

A *procedure* is a list of steps; each step removes one *fragment* (the tissue that one
or several forceps bites take out) with a closed, seeded, irregular cutter solid, and the
step's tissue is the previous one minus that cutter (manifold3d), so the steps are nested
by construction. Procedures (``docs/phantoms.md``, "Procedures"):

* ``uncinectomy``: the uncinate process (the airway-facing cap of the infundibulum's wall)
  is taken in ``n`` fragments from its free (inferior) edge upward, until the infundibulum
  and the view towards the maxillary ostium lie open: the first reaches just past the
  spot the endoscope is aimed at, the others share the rest of the cap's area
  (:func:`cap_schedule`).
* ``ethmoidectomy``: a shorter uncinectomy, then the anterior wall of the ethmoid bulla in
  fragments, then the walls between the bulla and the neighbouring anterior ethmoid cells.
* ``bites``: the small overlapping bites of :func:`phantoms.bites.plan_bites` (the fine
  change regime).

Every face a cutter creates is labelled (manifold3d keeps each triangle's original mesh
id): :func:`cut_steps` returns per step a boolean mask over the step mesh's faces.

Before a step is accepted it is checked: it must remove tissue, stay inside the
procedure's structures (the wall shells of the cells it opens) and keep away from the
tissue block's outer faces; otherwise :class:`~phantoms.errors.ProcedureError` names the
procedure (or plan entry) and the step.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import manifold3d as m3d
import numpy as np

from phantoms.anatomy import Anatomy, SphereCell, arrays_from_manifold
from phantoms.bites import plan_bites
from phantoms.cutters import (  # noqa: F401 - Fragment and exposed_cap are re-exported
    Fragment,
    _frame,
    _shell,
    _sphere,
    exposed_cap,
    fragment_cutter,
)
from phantoms.errors import (
    BiteMissError,
    ParameterRangeError,
    ProcedureError,
    UnknownProcedureError,
)

PROCEDURES: tuple[str, ...] = ("uncinectomy", "ethmoidectomy", "bites")
"""Procedures ``python -m phantoms generate --procedure`` accepts (first = default)."""

STEP_RANGES: dict[str, tuple[int, int]] = {
    "uncinectomy": (1, 8),
    "ethmoidectomy": (4, 12),
    "bites": (1, 20),
}
"""Allowed number of steps (``--bites N``) per procedure."""

FRAGMENT_SHARE_RANGE = (0.7, 1.3)
"""Relative size (share of the cap's area) of each fragment after the first, normalised
over those fragments."""
FIRST_PAST_TARGET_RANGE = (0.05, 0.15)
"""The uncinectomy's first fragment takes the free edge up to just past the target (the
spot the endoscope is aimed at, where the first bites go): its edge lies this much of the
cap's area above the target's height."""
FIRST_AREA_RANGE = (0.25, 0.8)
"""Bounds of the first fragment's share of the cap's area (a cap without a target, the
bulla, draws it in this range): at least a quarter, and at least a fifth is left for the
other fragments, so that no step is a sliver and none takes nearly the whole cap."""
# the upper end of uncinate_bulge_mm in phantoms.params.PARAM_RANGES (which imports this
# module to check procedures, hence a literal; a test keeps the two equal)
MAX_PROTRUSION_MM = {"infundibulum": 4.0}
"""The uncinate process is the part of the infundibulum's exposed wall within this depth
(the largest ``uncinate_bulge_mm``) of the cap's apex. Where the lateral wall recedes on
one side more of the sphere is exposed; a rim taken there (the cut is a plane at the rim's
depth) also cut the sphere's wall out of the solid lateral wall on every other side, and
the size of the surgery followed the recess rather than the uncinate."""
BITES_PER_FRAGMENT = (1, 3)
"""Forceps bites per fragment (the scallops of its cut edge)."""
RAGGED_MM = (0.35, 0.7)
"""Amplitude of the irregular cut edge, mm."""
PROGRESS_ROLL_DEG = 25.0
"""The direction of progress ("upward") is rolled about the cap axis by up to this."""
EDGE_TILT_DEG = 12.0
"""Each fragment's cut edge is tilted against the direction of progress by up to this."""
WALL_CUT_RADIUS_FRAC = (0.45, 0.7)
"""Radius of the opening in a wall between two ethmoid cells (fraction of the smaller)."""
CELL_REACH_MM = 3.5
"""A neighbouring ethmoid cell is in reach when the tissue between the voids is thinner."""
OUTSIDE_TOL_MM = 0.6
"""A fragment may reach this far beyond its structure's wall shell."""
OUTSIDE_VOLUME_TOL = (0.5, 0.05)
"""Removed tissue beyond the structures is refused above max(0.5 mm^3, 5 % of the step)."""
BLOCK_CLEARANCE_MM = 1.0
"""Removed tissue must stay this far inside the tissue block's outer faces."""
MIN_REMOVED_MM3 = 0.5


def check_procedure(name: object, n_steps: object) -> tuple[str, int]:
    """Return ``(name, n_steps)`` if the procedure exists and the count is in its range."""
    if name not in PROCEDURES:
        raise UnknownProcedureError(
            "procedure", f"unknown procedure {name!r}; expected one of {', '.join(PROCEDURES)}"
        )
    lo, hi = STEP_RANGES[str(name)]
    if isinstance(n_steps, bool) or not isinstance(n_steps, int | np.integer):
        raise ParameterRangeError(
            "n_bites",
            f"expected an integer number of steps (--bites) in [{lo}, {hi}], got {n_steps!r}",
        )
    if not lo <= int(n_steps) <= hi:
        raise ParameterRangeError(
            "n_bites",
            f"procedure {name} takes {lo}-{hi} steps (--bites), got {n_steps}",
        )
    return str(name), int(n_steps)


# ----------------------------------------------------------------------------- data


@dataclass(frozen=True)
class StepCut:
    """Tissue after one step and what the step removed."""

    tissue: m3d.Manifold
    cutter: m3d.Manifold
    removed: m3d.Manifold
    removed_volume_mm3: float
    cut_faces: np.ndarray
    """(F,) bool over the faces of ``arrays_from_manifold(tissue)``: True = a cut face."""


# ---------------------------------------------------------------------------- plans


def _cap_fragments(
    tissue: m3d.Manifold,
    cell: SphereCell,
    structure_label: str,
    n: int,
    rng: np.random.Generator,
    procedure: str,
    first_step: int,
    up_hint: np.ndarray,
    focus_mm: np.ndarray | None = None,
) -> list[Fragment]:
    """``n`` cumulative cap slices of the cell's exposed wall, from bottom to top.

    ``focus_mm``: the point the endoscope is aimed at (the target); the first fragment
    reaches just past it. Without it the first fragment's share is drawn in
    :data:`FIRST_AREA_RANGE`.
    """
    dirs, areas = exposed_cap(tissue, cell, with_areas=True)
    if len(dirs) < 10:
        raise ProcedureError(
            f"{procedure} step {first_step}",
            f"no {structure_label} wall in reach: the {cell.name}'s wall is not exposed to the "
            "airway (or what the earlier steps opened) in this phantom",
        )
    a = dirs.mean(axis=0)
    a /= np.linalg.norm(a)
    roll = math.radians(rng.uniform(-PROGRESS_ROLL_DEG, PROGRESS_ROLL_DEG))
    R = _frame(a, up_hint, roll)
    ro = cell.outer_radius_mm
    local = dirs @ R * ro  # (P, 3): side, depth, height on the outer sphere
    # keep clear of the rim where the wall runs into the lateral wall
    depth_min = float(np.quantile(local[:, 1], 0.08)) + 0.4
    if cell.name in MAX_PROTRUSION_MM:
        depth_min = max(depth_min, ro - MAX_PROTRUSION_MM[cell.name] + 0.4)
    keep = local[:, 1] >= depth_min
    if keep.sum() < 10:  # pragma: no cover - a patch always has an interior
        raise ProcedureError(
            f"{procedure} step {first_step}", f"the exposed {structure_label} is too small to cut"
        )
    cum = cap_schedule(local[keep, 2], areas[keep], n, rng, _height(focus_mm, cell, R))
    order = np.argsort(local[keep, 2])
    heights = local[keep, 2][order]
    cum_area = np.cumsum(areas[keep][order]) / areas[keep].sum()
    out = []
    for k in range(n):
        last = k == n - 1
        # the last fragment takes what is left of the cap, up to and past its top
        level = heights[-1] + 3.0 if last else float(np.interp(cum[k], cum_area, heights))
        out.append(
            Fragment(
                "cap",
                cell.name,
                {
                    "structure_label": structure_label,
                    "level_mm": round(level, 6),
                    "area_fraction": round(float(cum[k]), 6),
                    "depth_min_mm": round(depth_min, 6),
                    "edge_tilt_deg": round(float(rng.uniform(-EDGE_TILT_DEG, EDGE_TILT_DEG)), 6),
                    "ragged_mm": round(float(rng.uniform(*RAGGED_MM)), 6),
                    "n_bites": int(rng.integers(BITES_PER_FRAGMENT[0], BITES_PER_FRAGMENT[1] + 1)),
                    "edge_seed": int(rng.integers(2**31)),
                    "R_world_from_local": [[round(float(x), 12) for x in row] for row in R],
                },
            )
        )
    return out


def _height(point_mm: np.ndarray | None, cell: SphereCell, R: np.ndarray) -> float | None:
    """Height of a point in the cap's local frame (None stays None)."""
    if point_mm is None:
        return None
    return float((np.asarray(point_mm, float) - np.asarray(cell.center_mm)) @ R[:, 2])


def cap_schedule(
    heights_mm: np.ndarray,
    areas_mm2: np.ndarray,
    n: int,
    rng: np.random.Generator,
    focus_height_mm: float | None = None,
) -> np.ndarray:
    """Cumulative share of the cap's area taken after each of ``n`` fragments, (n,).

    heights_mm, areas_mm2 : (P,) height (along the direction of progress) and area of the
    cap's faces. The first fragment takes the area below ``focus_height_mm`` plus a share
    drawn in :data:`FIRST_PAST_TARGET_RANGE`, clipped to :data:`FIRST_AREA_RANGE` (without
    a focus: drawn in that range); the others share the rest in proportions drawn in
    :data:`FRAGMENT_SHARE_RANGE`; the last value is 1 (the whole cap).
    """
    shares = rng.uniform(*FRAGMENT_SHARE_RANGE, size=max(n - 1, 1))
    if focus_height_mm is None:
        first = float(rng.uniform(*FIRST_AREA_RANGE))
    else:
        below = float(areas_mm2[heights_mm <= focus_height_mm].sum() / areas_mm2.sum())
        past = float(rng.uniform(*FIRST_PAST_TARGET_RANGE))
        first = float(np.clip(below + past, *FIRST_AREA_RANGE))
    if n == 1:
        return np.ones(1)
    rest = (1.0 - first) * np.cumsum(shares) / shares.sum()
    return np.concatenate([[first], first + rest])


def plan_procedure(
    anatomy: Anatomy,
    procedure: str,
    n_steps: int,
    seed: int,
    target: str = "uncinate",
    bite_size_mm: tuple[float, float] = (2.0, 5.0),
):
    """The fragments of a procedure for this anatomy (seeded).

    Returns ``(target, fragments, cuts)``: the :class:`~phantoms.bites.Target` the
    endoscope views, one :class:`Fragment` per step, and the applied :class:`StepCut`\\ s
    (the plan depends on what earlier steps opened, so it is cut as it is planned).

    Raises :class:`ProcedureError` naming the procedure and the step when the phantom
    cannot take it (no wall in reach, a cut beyond the structures).
    """
    from phantoms.bites import find_target  # noqa: PLC0415 - avoid a cycle at import

    procedure, n_steps = check_procedure(procedure, n_steps)
    if procedure == "bites":
        tgt, bites = plan_bites(anatomy, target, n_steps, bite_size_mm, seed)
        frags = [Fragment("bites", target, {}, (b,)) for b in bites]
        allowed = plan_allowed_region(anatomy, procedure, target)
        cuts = cut_steps(anatomy, frags, procedure, allowed=allowed, edge_mm=0.3)
        return tgt, frags, cuts
    rng = np.random.default_rng([int(seed), 0xF355])
    up = np.array([0.0, 0.0, 1.0])
    infund = anatomy.cell("infundibulum")
    tgt, _, _ = find_target(anatomy, "uncinate")
    focus = np.asarray(tgt.center_mm, float)  # where the endoscope looks: the first bites
    if procedure == "uncinectomy":
        frags = _cap_fragments(
            anatomy.tissue, infund, "uncinate process", n_steps, rng, procedure, 1, up, focus
        )
        frags, cuts = _cut_with_retries(anatomy, frags, procedure, anatomy.tissue, 1, set())
        return tgt, frags, cuts
    # ethmoidectomy: uncinectomy, bulla's anterior wall, walls to the neighbouring cells
    n_u = 2 if n_steps <= 5 else 3
    n_wall_max = n_steps - n_u - 2
    bulla = anatomy.cell("ethmoid_bulla")
    neighbours = _reachable_cells(anatomy, bulla)
    n_w = min(len(neighbours), max(1, int(rng.integers(1, n_wall_max + 1))))
    if not neighbours:
        n_w = 0
    n_b = n_steps - n_u - n_w
    ids: set[int] = set()
    frags = _cap_fragments(
        anatomy.tissue, infund, "uncinate process", n_u, rng, procedure, 1, up, focus
    )
    frags, cuts = _cut_with_retries(anatomy, frags, procedure, anatomy.tissue, 1, ids)
    tissue = cuts[-1].tissue
    b_frags = _cap_fragments(tissue, bulla, "ethmoid bulla", n_b, rng, procedure, n_u + 1, up)
    b_frags, b_cuts = _cut_with_retries(anatomy, b_frags, procedure, tissue, n_u + 1, ids)
    cuts += b_cuts
    frags += b_frags
    if n_steps - n_u - n_b > 0 and not neighbours:
        raise ProcedureError(
            f"{procedure} step {n_u + n_b + 1}",
            f"no wall between anterior ethmoid cells in reach: no ethmoid cell lies within "
            f"{CELL_REACH_MM} mm of the opened bulla",
        )
    w_frags = []
    for cell in neighbours[:n_w]:
        r = min(bulla.radius_mm, cell.radius_mm) * float(rng.uniform(*WALL_CUT_RADIUS_FRAC))
        w_frags.append(
            Fragment(
                "wall",
                bulla.name,
                {
                    "structure_label": f"wall between the ethmoid bulla and {cell.name}",
                    "into": cell.name,
                    "radius_mm": round(r, 6),
                    "ragged_mm": round(float(rng.uniform(*RAGGED_MM)), 6),
                    "edge_seed": int(rng.integers(2**31)),
                },
            )
        )
    if w_frags:
        tissue = cuts[-1].tissue
        w_frags, w_cuts = _cut_with_retries(anatomy, w_frags, procedure, tissue, n_u + n_b + 1, ids)
        cuts += w_cuts
        frags += w_frags
    return tgt, frags, cuts


def _cut_with_retries(anatomy, frags, procedure, tissue, first_step, ids, tries: int = 6):
    """Cut the fragments in order; a fragment whose ragged edge pinches the tissue (an
    edge shared by four faces) is redrawn with the next edge seed, up to ``tries`` times."""
    frags = list(frags)
    cuts: list[StepCut] = []
    current = tissue
    for i in range(len(frags)):
        for attempt in range(tries):
            try:
                cut = cut_steps(
                    anatomy, [frags[i]], procedure, current, first_step + i, cutter_ids=ids
                )[0]
                break
            except ProcedureError as exc:
                if "touching itself" not in exc.problem or attempt == tries - 1:
                    raise
                p = dict(frags[i].params)
                p["edge_seed"] = int(p["edge_seed"]) + 1
                if "depth_min_mm" in p:  # and move the rim a little (the last cap fragment)
                    p["depth_min_mm"] = round(float(p["depth_min_mm"]) + 0.15, 6)
                frags[i] = dataclasses.replace(frags[i], params=p)
        cuts.append(cut)
        current = cut.tissue
    return frags, cuts


def _reachable_cells(anatomy: Anatomy, bulla: SphereCell) -> list[SphereCell]:
    """Further ethmoid cells whose void lies within CELL_REACH_MM of the bulla's, nearest first."""
    out = []
    for c in anatomy.cells:
        if not c.name.startswith("ethmoid_cell"):
            continue
        gap = (
            float(np.linalg.norm(np.subtract(c.center_mm, bulla.center_mm)))
            - c.radius_mm
            - bulla.radius_mm
        )
        if gap <= CELL_REACH_MM:
            out.append((gap, c.name, c))
    return [c for _, _, c in sorted(out, key=lambda t: (t[0], t[1]))]


def plan_allowed_region(anatomy: Anatomy, procedure: str, target: str) -> m3d.Manifold:
    """Where a user's plan may cut for a procedure: the wall shells (plus a margin) of the
    cells the procedure opens (``bites``: the target lamella's cell, 1.6 mm margin, as a
    bite spans the lamella plus 1.25 mm on either side)."""
    from phantoms.anatomy import TARGET_CELLS  # noqa: PLC0415

    if procedure == "bites":
        return _shell(anatomy.cell(TARGET_CELLS[target]), 1.6, 1.6)
    cells = [anatomy.cell("infundibulum")]
    if procedure == "ethmoidectomy":
        bulla = anatomy.cell("ethmoid_bulla")
        cells.append(bulla)
        solids = [
            m3d.Manifold.batch_hull(
                [
                    _sphere(bulla.center_mm, bulla.outer_radius_mm + OUTSIDE_TOL_MM, 0.5),
                    _sphere(c.center_mm, c.outer_radius_mm + OUTSIDE_TOL_MM, 0.5),
                ]
            )
            for c in _reachable_cells(anatomy, bulla)
        ]
    else:
        solids = []
    solids += [_shell(c, OUTSIDE_TOL_MM, OUTSIDE_TOL_MM) for c in cells]
    return m3d.Manifold.batch_boolean(solids, m3d.OpType.Add)


def _allowed_region(anatomy: Anatomy, frag: Fragment) -> m3d.Manifold:
    cell = anatomy.cell(frag.structure)
    if frag.kind == "wall":
        other = anatomy.cell(frag.params["into"])
        return m3d.Manifold.batch_hull(
            [
                _sphere(cell.center_mm, cell.outer_radius_mm + OUTSIDE_TOL_MM, 0.5),
                _sphere(other.center_mm, other.outer_radius_mm + OUTSIDE_TOL_MM, 0.5),
            ]
        )
    return _shell(cell, OUTSIDE_TOL_MM, OUTSIDE_TOL_MM)


def cut_steps(
    anatomy: Anatomy,
    fragments,
    procedure: str,
    tissue: m3d.Manifold | None = None,
    first_step: int = 1,
    allowed: m3d.Manifold | None | bool = True,
    where: str | None = None,
    edge_mm: float = 0.3,
    cutter_ids: set[int] | None = None,
) -> list[StepCut]:
    """Apply the fragments one after the other, checking each step.

    ``allowed``: True = each fragment's own structure (:func:`_allowed_region`), a
    manifold = that region for every step, None/False = no structure check (only the
    block check). ``where`` names the source in errors (default ``"<procedure> step k"``;
    a plan passes ``"<plan file> entry i"``). ``cutter_ids``: original ids of earlier
    steps' cutters (updated in place), so their faces stay labelled as cut faces.
    """
    current = anatomy.tissue if tissue is None else tissue
    cutter_ids = set() if cutter_ids is None else cutter_ids
    lo = np.asarray(anatomy.block_min_mm) + BLOCK_CLEARANCE_MM
    hi = np.asarray(anatomy.block_max_mm) - BLOCK_CLEARANCE_MM
    out: list[StepCut] = []
    for i, frag in enumerate(fragments):
        k = first_step + i
        name = where.format(i=i, k=k) if where else f"{procedure} step {k}"
        cutter = fragment_cutter(anatomy, frag, edge_mm)
        cutter_ids.add(int(cutter.original_id()))
        removed = current ^ cutter
        vol = 0.0 if removed.is_empty() else float(removed.volume())
        # a cap fragment's cutter holds the earlier fragments too: judge it by what it adds
        least = MIN_REMOVED_MM3 if frag.kind == "cap" else 0.01 * cutter.volume()
        if vol < max(MIN_REMOVED_MM3 * 0.1, least):
            raise BiteMissError(
                name,
                f"the fragment removes {vol:.3f} mm^3 of tissue (cutter {cutter.volume():.2f} mm^3): "
                "it misses the tissue",
            )
        box = removed.bounding_box()
        if np.any(np.asarray(box[:3]) < lo) or np.any(np.asarray(box[3:]) > hi):
            raise ProcedureError(
                name,
                f"the fragment would cut into the tissue block's outer walls (removed tissue "
                f"spans {np.round(box[:3], 2).tolist()}-{np.round(box[3:], 2).tolist()} mm, the "
                f"block's faces lie at {list(anatomy.block_min_mm)}-{list(anatomy.block_max_mm)} mm)",
            )
        region = _allowed_region(anatomy, frag) if allowed is True else (allowed or None)
        if region is not None:
            outside = removed - region
            out_vol = 0.0 if outside.is_empty() else float(outside.volume())
            limit = max(OUTSIDE_VOLUME_TOL[0], OUTSIDE_VOLUME_TOL[1] * vol)
            if out_vol > limit:
                label = frag.params.get("structure_label", frag.structure)
                raise ProcedureError(
                    name,
                    f"the fragment would cut {out_vol:.2f} mm^3 of tissue beyond the {label} "
                    f"(at most {limit:.2f} mm^3 allowed): it cuts past the procedure's structures",
                )
        after = current - cutter
        if _pinched(after):
            raise ProcedureError(
                name,
                "the cut leaves tissue touching itself along an edge or at a point (not a "
                "2-manifold once coincident vertices are merged); move the fragment",
            )
        current = after
        out.append(StepCut(current, cutter, removed, vol, _cut_mask(current, cutter_ids)))
    # labels accumulate over steps: faces from every earlier cutter stay cut faces
    return out


def _pinched(tissue: m3d.Manifold) -> bool:
    """True if merging coincident vertices makes an edge shared by more than two faces
    (trimesh and the simulator merge them when they load a mesh)."""
    v, f = arrays_from_manifold(tissue)
    # loaders merge vertices that agree to 8 decimals (trimesh's merge tolerance); one
    # byte key per vertex (+ 0.0 turns -0.0 into 0.0) sorts ~7x faster than unique rows
    r = np.ascontiguousarray(np.round(v, 8) + 0.0)
    key = r.view(np.dtype((np.void, 3 * r.dtype.itemsize))).ravel()
    _, inverse = np.unique(key, return_inverse=True)
    g = inverse.reshape(-1)[f].astype(np.int64)
    edges = np.sort(np.concatenate([g[:, [0, 1]], g[:, [1, 2]], g[:, [2, 0]]]), axis=1)
    code = np.sort(edges[:, 0] * (int(g.max()) + 1) + edges[:, 1])
    # an edge of more than two faces: the same code three times in a row once sorted
    return bool(np.any(code[2:] == code[:-2]))


def _cut_mask(tissue: m3d.Manifold, cutter_ids: set[int]) -> np.ndarray:
    mesh = tissue.to_mesh64()
    run_index = np.asarray(mesh.run_index, dtype=np.int64) // 3  # into tri_verts.ravel()
    run_ids = np.asarray(mesh.run_original_id, dtype=np.int64)
    n = len(np.asarray(mesh.tri_verts))
    mask = np.zeros(n, dtype=bool)
    for j, oid in enumerate(run_ids):
        if int(oid) in cutter_ids:
            mask[run_index[j] : run_index[j + 1]] = True
    return mask
