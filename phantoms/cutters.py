"""Fragment cutters: the closed, seeded, ragged solids that one surgical step removes.

A :class:`Fragment` describes one step's cutter: a ragged slice of a cell's exposed wall
("cap", below a ragged edge with one scallop per forceps bite), a ragged opening between
two cells ("wall"), or a union of forceps bites ("bites"). :func:`fragment_cutter` builds
it (manifold3d, marked as an original mesh so that its faces can be labelled as cut
faces). Used by :mod:`phantoms.procedures`, which plans and checks the steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import manifold3d as m3d
import numpy as np

from phantoms.anatomy import Anatomy, SphereCell, arrays_from_manifold, manifold_from_arrays
from phantoms.bites import Bite, cutter_manifold

# ----------------------------------------------------------------------------- data


@dataclass(frozen=True)
class Fragment:
    """One step's cutter: either a ragged cap slice, a ragged wall opening, or bites.

    kind : "cap" (all of a cell's exposed wall below a ragged edge), "wall" (an opening
    between two cells) or "bites" (a union of :class:`~phantoms.bites.Bite` cutters).
    structure : the cell whose wall it opens (``infundibulum`` = the uncinate process,
    ``ethmoid_bulla``, ...), or the plan / target name.
    """

    kind: str
    structure: str
    params: dict = field(default_factory=dict)
    bites: tuple[Bite, ...] = ()

    def to_dict(self) -> dict:
        d: dict = {"kind": self.kind, "structure": self.structure}
        d.update(self.params)
        if self.bites:
            d["bites"] = [b.to_dict() for b in self.bites]
        return d


# ------------------------------------------------------------------------ geometry


def _frame(a: np.ndarray, up_hint: np.ndarray, roll_rad: float) -> np.ndarray:
    """(3, 3) columns e1 (side), e2 = a (into the airway), e3 (direction of progress)."""
    a = a / np.linalg.norm(a)
    u = up_hint - (up_hint @ a) * a
    if np.linalg.norm(u) < 1e-6:
        u = np.array([0.0, 1.0, 0.0]) - a[1] * a
    u /= np.linalg.norm(u)
    v = np.cross(a, u)
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    u, v = c * u + s * v, -s * u + c * v
    return np.stack([v, a, u], axis=1)


def _noise_2d(rng: np.random.Generator, amplitude: float, n_waves: int = 7):
    """A seeded smooth-plus-jagged 2-D field of peak ~amplitude (mm): wavelengths 0.8-4 mm."""
    ang = rng.uniform(0, 2 * math.pi, n_waves)
    lam = rng.uniform(0.8, 4.0, n_waves)
    k = np.stack([np.cos(ang), np.sin(ang)], axis=1) * (2 * math.pi / lam)[:, None]
    ph = rng.uniform(0, 2 * math.pi, n_waves)
    w = rng.uniform(0.5, 1.0, n_waves)
    w *= amplitude / w.sum() * 2.0

    def f(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        out = np.zeros_like(x)
        for kk, p, ww in zip(k, ph, w, strict=True):
            out += ww * np.sin(kk[0] * x + kk[1] * y + p)
        return out

    return f


def _heightfield_solid(
    R_world_from_local: np.ndarray,
    origin: np.ndarray,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    z_bottom: float,
    z_top,
    step_mm: float = 0.25,
) -> m3d.Manifold:
    """Closed solid {x, y in the ranges, z_bottom <= z <= z_top(x, y)} in a local frame."""
    nx = max(2, int(math.ceil((x_range[1] - x_range[0]) / step_mm)) + 1)
    ny = max(2, int(math.ceil((y_range[1] - y_range[0]) / step_mm)) + 1)
    xs = np.linspace(*x_range, nx)
    ys = np.linspace(*y_range, ny)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    Z = z_top(X, Y)
    top = np.stack([X, Y, Z], axis=-1).reshape(-1, 3)
    bot = np.stack([X, Y, np.full_like(X, z_bottom)], axis=-1).reshape(-1, 3)
    verts = np.vstack([top, bot])
    idx = np.arange(nx * ny).reshape(nx, ny)
    nt = nx * ny
    faces = []
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    # top faces up (+z), bottom faces down
    faces.append(np.stack([a, b, c], -1).reshape(-1, 3))
    faces.append(np.stack([a, c, d], -1).reshape(-1, 3))
    faces.append(np.stack([a + nt, c + nt, b + nt], -1).reshape(-1, 3))
    faces.append(np.stack([a + nt, d + nt, c + nt], -1).reshape(-1, 3))
    # four sides: walk the boundary counter-clockwise seen from +z
    ring = np.concatenate([idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]])
    nxt = np.roll(ring, -1)
    faces.append(np.stack([ring, ring + nt, nxt + nt], -1))
    faces.append(np.stack([ring, nxt + nt, nxt], -1))
    f = np.vstack(faces)
    world = verts @ R_world_from_local.T + origin
    man = manifold_from_arrays(world, f, "fragment cutter")
    if man.volume() < 0:  # pragma: no cover - orientation fixed above
        man = manifold_from_arrays(world, f[:, ::-1], "fragment cutter")
    return man


def _sphere(center, radius: float, edge_mm: float = 0.3) -> m3d.Manifold:
    n = int(max(32, 4 * math.ceil(2 * math.pi * radius / edge_mm / 4)))
    return m3d.Manifold.sphere(radius, n).translate(tuple(float(c) for c in center))


def _shell(cell: SphereCell, inner_pad: float, outer_pad: float) -> m3d.Manifold:
    return _sphere(cell.center_mm, cell.outer_radius_mm + outer_pad) - _sphere(
        cell.center_mm, max(cell.radius_mm - inner_pad, 0.2)
    )


def exposed_cap(
    tissue: m3d.Manifold, cell: SphereCell, tol_mm: float = 0.05, with_areas: bool = False
):
    """(P, 3) unit directions from the cell centre to the faces of the tissue surface that
    lie on the cell's outer wall sphere (its exposed, airway-facing wall); with
    ``with_areas`` also their (P,) areas in mm^2."""
    v, f = arrays_from_manifold(tissue)
    c = np.asarray(cell.center_mm)
    on = np.abs(np.linalg.norm(v - c, axis=1) - cell.outer_radius_mm) < tol_mm
    tri = v[f[on[f].all(axis=1)]]
    cen = tri.mean(axis=1) - c
    dirs = cen / np.linalg.norm(cen, axis=1, keepdims=True)
    if not with_areas:
        return dirs
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return dirs, areas


# -------------------------------------------------------------------------- cutters


def cap_cutter(anatomy: Anatomy, frag: Fragment) -> m3d.Manifold:
    """The ragged cutter of a "cap" fragment: the cell's wall shell below a ragged edge.

    A wall point is cut when its radial projection onto the outer wall sphere lies below
    the ragged edge and at least ``depth_min_mm`` towards the airway, as
    :func:`phantoms.procedures._cap_fragments` planned on that sphere. Every side of the
    cutter is a cone through the cell's centre, so the cut crosses the wall square to it,
    as forceps cut a lamella. A planar side cut the wall at up to ~40 deg and left wedge
    tips 0.04-0.5 mm thick (median 0.2 mm), thinner than the CT's voxel: no CT and no
    model on a 0.5 mm grid holds them, and they dominated every method's error
    (docs/phantoms.md).
    """
    p = frag.params
    cell = anatomy.cell(frag.structure)
    R = np.asarray(p["R_world_from_local"], float)
    c = np.asarray(cell.center_mm, float)
    ro = cell.outer_radius_mm
    rng = np.random.default_rng([int(p["edge_seed"]), 0xC07])
    noise = _noise_2d(rng, float(p["ragged_mm"]))
    n_b = int(p["n_bites"])
    level, tilt = float(p["level_mm"]), math.tan(math.radians(float(p["edge_tilt_deg"])))
    span = 2.0 * ro + 4.0
    scallop = 0.6 * float(p["ragged_mm"]) + 0.4

    def top(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        phase = (x + span / 2) / span * n_b * math.pi
        return level + tilt * x + noise(x, y) - scallop * (1.0 - np.abs(np.sin(phase)))

    def depth_on_sphere(x: np.ndarray, z: np.ndarray) -> np.ndarray:
        return np.sqrt(np.maximum(ro**2 - x**2 - z**2, 1e-6))

    def edge(x: np.ndarray, _t: np.ndarray) -> np.ndarray:
        # the edge on the outer sphere: z = top(x, y) with y the sphere's depth at (x, z)
        z = level + tilt * x
        for _ in range(3):
            z = top(x, depth_on_sphere(x, z))
        return z

    # the cutter in (x, t, z): x, z = the outer-sphere point's side and height, t = radius
    rho = math.sqrt(ro**2 - max(float(p["depth_min_mm"]), 0.05 * ro) ** 2)
    t_lo, t_hi = max(cell.radius_mm - 0.8, 0.1), ro + 0.9
    slab = _heightfield_solid(np.eye(3), np.zeros(3), (-rho, rho), (t_lo, t_hi), -rho - 1.0, edge)
    n_seg = int(max(32, math.ceil(2 * math.pi * rho / 0.3)))
    disc = (
        m3d.Manifold.cylinder(t_hi - t_lo + 2.0, rho, rho, n_seg)
        .rotate((-90.0, 0.0, 0.0))
        .translate((0.0, t_lo - 1.0, 0.0))
    )

    def radial(v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, float)
        x, t, z = v[:, 0], v[:, 1], v[:, 2]
        d = np.stack([x, depth_on_sphere(x, z), z], axis=1) / ro
        return c + (d * t[:, None]) @ R.T

    cone = (slab ^ disc).refine_to_length(0.3).warp_batch(radial)
    return (cone ^ _shell(cell, 0.4, 0.5)).as_original()


def wall_cutter(anatomy: Anatomy, frag: Fragment) -> m3d.Manifold:
    """The ragged cutter of a "wall" fragment: a warped capsule from one cell to the other."""
    p = frag.params
    a = np.asarray(anatomy.cell(frag.structure).center_mm, float)
    b = np.asarray(anatomy.cell(p["into"]).center_mm, float)
    r = float(p["radius_mm"])
    caps = [_sphere(a, r, 0.35), _sphere(b, r, 0.35)]
    hull = m3d.Manifold.batch_hull(caps).refine_to_length(0.35)
    rng = np.random.default_rng([int(p["edge_seed"]), 0xA11])
    amp = float(p["ragged_mm"])
    dirs = rng.normal(size=(6, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    lam = rng.uniform(0.8, 3.0, 6)
    ph = rng.uniform(0, 2 * math.pi, 6)
    axis = (b - a) / np.linalg.norm(b - a)

    def warp(v: np.ndarray) -> np.ndarray:
        v = np.asarray(v, float)
        rel = v - a
        t = rel @ axis
        radial = rel - np.outer(t, axis)
        nrm = np.linalg.norm(radial, axis=1, keepdims=True)
        unit = np.where(nrm > 1e-9, radial / np.maximum(nrm, 1e-9), 0.0)
        n = np.zeros(len(v))
        for d, lm, pp in zip(dirs, lam, ph, strict=True):
            n += np.sin(2 * math.pi / lm * (v @ d) + pp)
        return v + unit * (amp / 3.0 * n)[:, None]

    return hull.warp_batch(warp).as_original()


def fragment_cutter(anatomy: Anatomy, frag: Fragment, edge_mm: float = 0.3) -> m3d.Manifold:
    """The closed cutter solid of one step (world mm), marked as an original mesh."""
    if frag.kind == "cap":
        return cap_cutter(anatomy, frag)
    if frag.kind == "wall":
        return wall_cutter(anatomy, frag)
    solids = [cutter_manifold(b, edge_mm) for b in frag.bites]
    return m3d.Manifold.batch_boolean(solids, m3d.OpType.Add).as_original()
