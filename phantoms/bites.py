"""Surgical bites: a plan of forceps-sized cutters on a target lamella, applied by booleans.

A *bite* is a closed cutter solid (an ellipsoid or a rounded box, 2-5 mm jaws) placed
across the target lamella. :func:`plan_bites` puts the first bite at the centre of the
lamella's airway-facing surface and walks the next ones along that surface, each
overlapping the previous opening by ~40 %, so the bites widen one opening.
:func:`apply_bites` subtracts them one after the other and records the tissue each one
removes (``cutter ∩ tissue``); a bite that removes (almost) nothing raises
:class:`~phantoms.errors.BiteMissError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import manifold3d as m3d
import numpy as np
from scipy.spatial import cKDTree

from chisel.core.geometry import vec3
from phantoms.anatomy import TARGET_CELLS, Anatomy, SphereCell, arrays_from_manifold
from phantoms.ct import SurfaceDistance
from phantoms.errors import BiteMissError, ParameterRangeError, UnknownTargetError

MIN_REMOVED_FRACTION = 0.01
"""A bite must remove at least this fraction of its cutter's volume, else it missed."""


@dataclass(frozen=True)
class Bite:
    """One cutter of the plan.

    center_mm : (3,) float, world mm, the cutter's centre.
    size_mm : (3,) float, mm, full extent along the cutter's axes (jaw width, jaw
        length, depth through the lamella).
    R_world_from_cutter : (3, 3) float, rotation; column 2 is the depth axis.
    shape : "ellipsoid" or "rounded_box".
    """

    center_mm: tuple[float, float, float]
    size_mm: tuple[float, float, float]
    R_world_from_cutter: tuple[tuple[float, float, float], ...]
    shape: Literal["ellipsoid", "rounded_box"] = "ellipsoid"

    def __post_init__(self) -> None:
        c = np.asarray(self.center_mm, float)
        s = np.asarray(self.size_mm, float)
        R = np.asarray(self.R_world_from_cutter, float)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ParameterRangeError(
                "bite.center_mm", f"expected 3 finite numbers, got {self.center_mm!r}"
            )
        if s.shape != (3,) or not np.all(np.isfinite(s)) or s.min() <= 0.1 or s.max() > 20.0:
            raise ParameterRangeError(
                "bite.size_mm", f"expected 3 sizes in (0.1, 20] mm, got {self.size_mm!r}"
            )
        if (
            R.shape != (3, 3)
            or not np.allclose(R.T @ R, np.eye(3), atol=1e-6)
            or np.linalg.det(R) < 0
        ):
            raise ParameterRangeError("bite.R_world_from_cutter", "expected a 3x3 rotation matrix")
        if self.shape not in ("ellipsoid", "rounded_box"):
            raise ParameterRangeError(
                "bite.shape", f"expected 'ellipsoid' or 'rounded_box', got {self.shape!r}"
            )

    def to_dict(self) -> dict:
        return {
            "center_mm": [round(float(v), 6) for v in self.center_mm],
            "size_mm": [round(float(v), 6) for v in self.size_mm],
            "R_world_from_cutter": [
                [round(float(v), 9) for v in row] for row in self.R_world_from_cutter
            ],
            "shape": self.shape,
        }


@dataclass(frozen=True)
class Target:
    """Where the plan starts: the first bite's centre on the lamella surface facing the airway.

    center_mm : (3,) float, world mm.  normal : (3,) float unit vector from that surface
    into the airway.  thickness_mm : lamella thickness there.
    """

    name: str
    center_mm: tuple[float, float, float]
    normal: tuple[float, float, float]
    thickness_mm: float


@dataclass(frozen=True)
class BiteResult:
    """Tissue after one bite. removed_volume_mm3 = volume(cutter ∩ tissue before)."""

    tissue: m3d.Manifold
    cutter: m3d.Manifold
    removed: m3d.Manifold
    removed_volume_mm3: float


def cutter_manifold(bite: Bite, edge_mm: float = 0.3) -> m3d.Manifold:
    """The bite's closed cutter solid in world mm."""
    s = np.asarray(bite.size_mm, float) / 2.0
    n = int(max(24, 4 * math.ceil(math.pi * s.max() / edge_mm / 2.0)))
    if bite.shape == "ellipsoid":
        solid = m3d.Manifold.sphere(1.0, n).scale(tuple(s))
    else:
        # rounded box: hull of 8 corner spheres (jaw-like, rounded cup)
        r = 0.35 * float(s.min())
        corners = [
            m3d.Manifold.sphere(r, max(16, n // 2)).translate(
                (sx * (s[0] - r), sy * (s[1] - r), sz * (s[2] - r))
            )
            for sx in (-1, 1)
            for sy in (-1, 1)
            for sz in (-1, 1)
        ]
        solid = m3d.Manifold.batch_hull(corners)
    R = np.asarray(bite.R_world_from_cutter, float)
    affine = np.concatenate([R, np.asarray(bite.center_mm, float)[:, None]], axis=1)
    return solid.transform(affine.tolist())


def apply_bites(
    tissue: m3d.Manifold, bites: list[Bite] | tuple[Bite, ...], edge_mm: float = 0.3
) -> list[BiteResult]:
    """Subtract the bites one after the other.

    Returns one :class:`BiteResult` per bite: ``tissue_k = tissue_{k-1} - cutter_k``.

    Raises
    ------
    BiteMissError
        If a cutter removes less than :data:`MIN_REMOVED_FRACTION` of its own volume
        (it lies in air, or only grazes the tissue).
    """
    results: list[BiteResult] = []
    current = tissue
    for k, bite in enumerate(bites, start=1):
        cutter = cutter_manifold(bite, edge_mm)
        removed = current ^ cutter
        removed_volume = removed.volume() if not removed.is_empty() else 0.0
        if removed_volume < MIN_REMOVED_FRACTION * cutter.volume():
            raise BiteMissError(
                f"bite {k}",
                f"cutter at {np.round(bite.center_mm, 2).tolist()} mm removes {removed_volume:.4f} mm^3 of tissue, "
                f"expected at least {MIN_REMOVED_FRACTION:.0%} of its {cutter.volume():.2f} mm^3: it misses the tissue",
            )
        current = current - cutter
        results.append(BiteResult(current, cutter, removed, float(removed_volume)))
    return results


# ---------------------------------------------------------------------------- plan


def _exposed_patch(tissue: m3d.Manifold, cell: SphereCell, tol_mm: float = 0.05):
    """Faces of the tissue surface lying on the cell's outer wall sphere (the lamella's
    airway-facing side). Returns (vertices, faces, patch_mask)."""
    v, f = arrays_from_manifold(tissue)
    c = np.asarray(cell.center_mm)
    on = np.abs(np.linalg.norm(v - c, axis=1) - cell.outer_radius_mm) < tol_mm
    patch = on[f].all(axis=1)
    return v, f, patch


def find_target(anatomy: Anatomy, name: str) -> tuple[Target, SphereCell, np.ndarray]:
    """The target lamella's first-bite point, its normal into the airway, and the patch.

    The exposed patch is the part of the lamella's airway-facing wall sphere that lies on
    the tissue surface. The point is chosen among patch points at least 2.5 mm inside
    its rim (or 60 % of the deepest) as the one facing the most open airway.

    Returns the :class:`Target`, its cell and the (P, 3) float centroids (mm) of the
    exposed patch's faces.

    Raises
    ------
    UnknownTargetError
        If ``name`` is not a lamella of the phantom, or it is not exposed to the airway.
    """
    if name not in TARGET_CELLS:
        raise UnknownTargetError(
            "target",
            f"no lamella {name!r} in the phantom; expected one of {', '.join(TARGET_CELLS)}",
        )
    cell = anatomy.cell(TARGET_CELLS[name])
    v, f, patch = _exposed_patch(anatomy.tissue, cell)
    if patch.sum() < 10:
        raise UnknownTargetError(
            "target", f"lamella {name!r} is not exposed to the airway in this phantom"
        )
    tri = v[f]
    centroids = tri.mean(axis=1)
    patch_c = centroids[patch]
    # the patch's rim: vertices of patch faces shared with non-patch faces
    in_patch = np.zeros(len(v), bool)
    in_patch[f[patch].ravel()] = True
    in_other = np.zeros(len(v), bool)
    in_other[f[~patch].ravel()] = True
    rim = v[in_patch & in_other]
    rim_dist, _ = cKDTree(rim).query(patch_c)
    c = np.asarray(cell.center_mm)
    normals = patch_c - c
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # Candidates: well inside the patch (a bite fits). Among them prefer the point that
    # faces the most open airway: the clearance at 8, 10, 12 mm along its normal, where
    # that point is in direct sight, so an endoscope can view it from there.
    interior = rim_dist >= min(2.5, 0.6 * float(rim_dist.max()))
    idx = np.flatnonzero(interior)
    surface = SurfaceDistance(v, f)
    openness = np.full(len(idx), -np.inf)
    origins = c + (cell.outer_radius_mm + 0.05) * normals[idx]
    t_hit = surface.first_hit(origins, normals[idx])
    for d in (8.0, 10.0, 12.0):
        q = origins + d * normals[idx]
        free = surface.distance(q)
        free[(t_hit < d + 3.0) | surface.inside(q)] = -np.inf
        openness = np.maximum(openness, free)
    # 0.5 mm bins of openness, ties broken by the distance to the rim
    best = int(idx[np.lexsort((-rim_dist[idx], -np.floor(openness / 0.5)))[0]])
    n = normals[best]
    center = c + cell.outer_radius_mm * n
    target = Target(name, vec3(center), vec3(n), cell.wall_mm)
    return target, cell, patch_c


def _rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * K + (1 - math.cos(angle_rad)) * K @ K


def plan_bites(
    anatomy: Anatomy,
    target: str = "uncinate",
    n_bites: int = 5,
    size_range_mm: tuple[float, float] = (2.0, 5.0),
    seed: int = 0,
) -> tuple[Target, list[Bite]]:
    """A plan of ``n_bites`` adjacent bites that progressively widen one opening.

    The first bite is centred on the target's exposed surface (:func:`find_target`); the
    following ones step along the lamella (a great circle of its wall sphere) in the
    direction where the exposed patch extends furthest, each centre ~0.6 jaw widths from
    the previous one. Jaw width and length are drawn from ``size_range_mm``; the depth
    spans the lamella plus 1.25 mm on either side; the roll about the lamella normal
    (±25°), a tilt (≤10°) and the shape (ellipsoid or rounded box) are random.
    """
    tgt, cell, patch_c = find_target(anatomy, target)
    rng = np.random.default_rng([int(seed), 0xB17E])
    c = np.asarray(cell.center_mm)
    n0 = np.asarray(tgt.normal)
    # tangent direction: principal axis of the patch around the start, towards more patch
    rel = patch_c - np.asarray(tgt.center_mm)
    rel_t = rel - np.outer(rel @ n0, n0)
    near = np.linalg.norm(rel_t, axis=1) < 12.0
    _, _, vt = np.linalg.svd(rel_t[near] - rel_t[near].mean(axis=0), full_matrices=False)
    u = vt[0] - (vt[0] @ n0) * n0
    u /= np.linalg.norm(u)
    if (rel_t[near] @ u > 0).sum() < (rel_t[near] @ u < 0).sum():
        u = -u
    r_mid = cell.radius_mm + cell.wall_mm / 2.0
    depth = cell.wall_mm + 2.5
    lo, hi = size_range_mm
    widths = rng.uniform(lo, hi, size=n_bites)
    lengths = rng.uniform(lo, hi, size=n_bites)
    rolls = np.deg2rad(rng.uniform(-25.0, 25.0, size=n_bites))
    tilts = np.deg2rad(rng.uniform(0.0, 10.0, size=n_bites))
    tilt_dirs = rng.uniform(0.0, 2.0 * math.pi, size=n_bites)
    shapes = rng.integers(0, 2, size=n_bites)
    # the patch's extent either side of the start, along u (arc length on the mid sphere)
    proj = rel_t @ u
    room = {1: float(proj.max(initial=0.0)), -1: float(-proj.min(initial=0.0))}
    edge = {1: widths[0] / 2.0, -1: widths[0] / 2.0}
    arcs = [0.0]
    for k in range(1, n_bites):
        # widen the opening on the side with more lamella left; ~30 % overlap
        side = 1 if room[1] - edge[1] >= room[-1] - edge[-1] else -1
        centre = edge[side] + 0.2 * widths[k]
        edge[side] = centre + widths[k] / 2.0
        arcs.append(side * centre)
    bites: list[Bite] = []
    axis = np.cross(n0, u)
    for k in range(n_bites):
        R_step = _rotation(axis, arcs[k] / r_mid)
        radial = R_step @ n0
        along = R_step @ u
        lateral = np.cross(radial, along)
        R = np.stack([along, lateral, radial], axis=1)
        R = R @ _rotation(np.array([0.0, 0.0, 1.0]), rolls[k])
        tilt_axis = np.array([math.cos(tilt_dirs[k]), math.sin(tilt_dirs[k]), 0.0])
        R = R @ _rotation(tilt_axis, tilts[k])
        center = c + r_mid * radial
        bites.append(
            Bite(
                center_mm=vec3(center),
                size_mm=(float(widths[k]), float(lengths[k]), float(depth)),
                R_world_from_cutter=tuple(vec3(row) for row in R),
                shape="ellipsoid" if shapes[k] == 0 else "rounded_box",
            )
        )
    return tgt, bites
