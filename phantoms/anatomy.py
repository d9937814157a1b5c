"""Procedural nasal-sinus anatomy: the tissue solid of one nasal side as a manifold.

Construction (all lengths in mm, world frame of ``docs/phantoms.md``: +x lateral, +y
posterior, +z superior; the septum's midline face lies near x = 0, the nostril at y = 0,
the nasal floor at z = 0):

1. The **airway** is an implicit field (positive in air; :class:`phantoms.airway.AirwayField`):
   the space between septum and lateral wall, floor and roof, with the three turbinates
   carved out by smooth subtraction and a smooth low-frequency undulation of the walls.
   It is sampled on a grid and meshed with marching cubes (scikit-image), then made a
   manifold.
2. Every **air cell** (infundibulum behind the uncinate process, ethmoid bulla, posterior
   ethmoid cell behind the basal lamella, further ethmoid cells, maxillary sinus with its
   ostium) is a void ``V`` with a wall ``W``: ``V`` dilated by the wall thickness. The
   walls are subtracted from the airway, so a wall that meets the airway bulges into it
   as a lamella of exactly that thickness (spheres are used where the thickness must be
   exact), and no void ever touches the airway.
3. ``tissue = block - (airway - walls) - voids``: a closed, oriented 2-manifold whose
   outer shell includes the airway (open at the nostril, y = 0) and one inner shell per
   closed air cell.

The bulla, basal lamella and uncinate are the bite targets (:data:`TARGET_CELLS`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import manifold3d as m3d
import numpy as np
from skimage.measure import marching_cubes

from chisel.core.geometry import vec3
from phantoms.airway import AirwayField
from phantoms.errors import AnatomyError, NotManifoldError

#: target lamella -> the air cell whose airway-facing wall it is.
TARGET_CELLS: dict[str, str] = {
    "uncinate": "infundibulum",
    "bulla": "ethmoid_bulla",
    "basal_lamella": "posterior_ethmoid",
}

_SEPTUM_FACE_X = -3.5  # medial face of the tissue block (midline of the septum), mm


@dataclass(frozen=True)
class SphereCell:
    """A spherical air cell: void of ``radius_mm`` inside a wall ``wall_mm`` thick."""

    name: str
    center_mm: tuple[float, float, float]
    radius_mm: float
    wall_mm: float

    @property
    def outer_radius_mm(self) -> float:
        return self.radius_mm + self.wall_mm


@dataclass(frozen=True)
class Anatomy:
    """The preoperative tissue solid and the geometry the rest of the generator needs."""

    tissue: m3d.Manifold
    """Closed tissue solid (block minus airway minus air cells), mm."""
    cells: tuple[SphereCell, ...]
    """Spherical air cells, targets first (infundibulum, bulla, posterior ethmoid)."""
    maxillary_center_mm: tuple[float, float, float]
    maxillary_semi_axes_mm: tuple[float, float, float]
    maxillary_volume_mm3: float
    """Volume of the maxillary sinus void alone (without ostium and infundibulum), mm^3."""
    block_min_mm: tuple[float, float, float]
    block_max_mm: tuple[float, float, float]
    nostril_mm: tuple[float, float, float]
    """Centre of the nostril opening on the block's anterior face (y = 0)."""
    airway_min_mm: tuple[float, float, float]
    airway_max_mm: tuple[float, float, float]
    """Bounding box of the airway inside the block, mm."""
    n_voids: int
    """Number of closed air voids (inner surface shells) of ``tissue``."""

    def cell(self, name: str) -> SphereCell:
        for c in self.cells:
            if c.name == name:
                return c
        raise KeyError(name)


# ------------------------------------------------------------------------- meshing


def manifold_from_arrays(
    vertices: np.ndarray, faces: np.ndarray, source: str = "mesh"
) -> m3d.Manifold:
    """Closed manifold from a triangle mesh, or :class:`NotManifoldError`.

    vertices : (V, 3) float, mm.  faces : (F, 3) int, counter-clockwise seen from outside.
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.uint64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise NotManifoldError(
            source, f"expected (V, 3) vertices and (F>0, 3) faces, got {v.shape} and {f.shape}"
        )
    man = m3d.Manifold(m3d.Mesh64(vert_properties=v, tri_verts=f))
    if man.status() != m3d.Error.NoError or man.is_empty():
        raise NotManifoldError(
            source,
            f"not a closed oriented 2-manifold (manifold3d status {man.status().name}); "
            "repair it first (phantoms.repair_surface or `python -m phantoms repair`)",
        )
    return man


def arrays_from_manifold(man: m3d.Manifold) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) float64 vertices in mm and (F, 3) int64 faces of a manifold."""
    mesh = man.to_mesh64()
    v = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3].copy()
    f = np.asarray(mesh.tri_verts, dtype=np.int64).copy()
    return v, f


def mesh_field(field, lo: np.ndarray, hi: np.ndarray, step_mm: float) -> m3d.Manifold:
    """Marching-cubes mesh of ``{field > 0}`` inside the box ``[lo, hi]`` as a manifold."""
    n = np.ceil((hi - lo) / step_mm).astype(int) + 1
    axes = [lo[i] + step_mm * np.arange(n[i]) for i in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    vol = field(X, Y, Z).astype(np.float32)
    vol = np.pad(vol, 1, constant_values=-1.0)  # closes the surface at the box faces
    verts, faces, _, _ = marching_cubes(
        vol, level=0.0, spacing=(step_mm,) * 3, allow_degenerate=False
    )
    verts = verts.astype(np.float64) + (lo - step_mm)
    man = manifold_from_arrays(verts, faces[:, ::-1], "airway marching cubes")
    if man.volume() < 0:  # pragma: no cover - orientation is fixed by the reversal above
        man = manifold_from_arrays(verts, faces, "airway marching cubes")
    return man


AIR_POCKET_MAX_MM3 = 1.0
"""A part of the airway's mesh smaller than this is a pocket that marching cubes pinched
off the field, not anatomy."""


def drop_air_pockets(man: m3d.Manifold, max_mm3: float = AIR_POCKET_MAX_MM3) -> m3d.Manifold:
    """``man`` without its connected parts smaller than ``max_mm3``.

    The airway field can close a pocket far smaller than a voxel off the airway (seed 1233:
    0.1 mm^3, 0.2 mm thin, beside the olfactory cleft); left in, it became a closed air void
    that no cell explains, and the generator refused the seed. A mesh of one part is
    returned as it is (the same bytes as before this rule).
    """
    parts = man.decompose()
    if len(parts) <= 1:
        return man
    kept = [part for part in parts if part.volume() >= max_mm3]
    return kept[0] if len(kept) == 1 else m3d.Manifold.compose(kept)


def airway_grid_mm(edge_mm: float, p: dict[str, float]) -> float:
    """Marching-cubes step of the airway: the surface edge length, but at most half the
    olfactory cleft's width (so the cleft never pinches off) and at most 1 mm."""
    return float(min(edge_mm, 0.5 * p["roof_width_mm"], 1.0))


def _segments(radius: float, edge_mm: float) -> int:
    return int(max(16, 4 * math.ceil(2.0 * math.pi * radius / edge_mm / 4.0)))


def sphere(center, radius: float, edge_mm: float) -> m3d.Manifold:
    return m3d.Manifold.sphere(radius, _segments(radius, edge_mm)).translate(
        tuple(float(c) for c in center)
    )


# ----------------------------------------------------------------------- the build


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1.0 - 2.0 * i / n)
    theta = math.pi * (1.0 + 5.0**0.5) * i
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


_UNIT = _fibonacci_sphere(600)


def _inside_ellipsoid(points: np.ndarray, center, axes) -> np.ndarray:
    q = (points - np.asarray(center)) / np.asarray(axes)
    return np.einsum("ij,ij->i", q, q) <= 1.0


def _sphere_hits_ellipsoid(c, r: float, e_center, e_axes) -> bool:
    """True if the ball (c, r) reaches into the ellipsoid (surface samples, mm)."""
    pts = np.asarray(c) + r * _UNIT
    return bool(_inside_ellipsoid(np.vstack([pts, np.asarray(c)[None]]), e_center, e_axes).any())


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = float(np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


def build_anatomy(p: dict[str, float], seed: int, edge_mm: float = 0.5) -> Anatomy:
    """Build the preoperative tissue solid from sampled shape parameters.

    Parameters
    ----------
    p : dict
        Shape parameters (:func:`phantoms.params.sample_params`).
    seed : int
        Seed of the wall undulation and of the further ethmoid cells' placement.
    edge_mm : float
        Target edge length of the surface, mm (the airway grid: :func:`airway_grid_mm`).

    Raises
    ------
    AnatomyError
        If the air cells cannot be placed without touching each other.
    """
    air = AirwayField(p, seed)
    targets = _target_cells(air, p)
    m_center, m_axes = _maxillary_sinus(air, p, targets)
    cells = [*targets, *_ethmoid_cells(air, p, seed, targets, m_center, m_axes)]
    tissue, maxillary_volume, b_lo, b_hi, air_lo, air_hi = _tissue_solid(
        air, p, cells, m_center, m_axes, edge_mm
    )
    # closed voids = shells beyond the outer one; the infundibulum, ostium and maxillary
    # sinus form one void
    expected_voids = len(cells)  # (cells - infundibulum) + the infundibulum-maxillary void
    n_shells = _count_shells(tissue)
    if n_shells - 1 != expected_voids:
        raise AnatomyError(
            "anatomy",
            f"expected {expected_voids} closed air voids, got {n_shells - 1}; air cells touch each other or the airway",
        )
    return Anatomy(
        tissue=tissue,
        cells=tuple(cells),
        maxillary_center_mm=vec3(m_center),
        maxillary_semi_axes_mm=vec3(m_axes),
        maxillary_volume_mm3=float(maxillary_volume),
        block_min_mm=vec3(b_lo),
        block_max_mm=vec3(b_hi),
        nostril_mm=_nostril(air, p),
        airway_min_mm=vec3(np.maximum(air_lo, b_lo)),
        airway_max_mm=vec3(np.minimum(air_hi, b_hi)),
        n_voids=expected_voids,
    )


def _wall_x(air: AirwayField, y: float, z: float) -> float:
    """x of the airway's lateral wall at (y, z), mm."""
    return float(air.lateral_x(np.array(y), np.array(z)))


def _target_cells(
    air: AirwayField, p: dict[str, float]
) -> tuple[SphereCell, SphereCell, SphereCell]:
    """The infundibulum (behind the uncinate), the ethmoid bulla and the posterior ethmoid
    cell (behind the basal lamella), front to back along the lateral wall; each next cell
    starts where it clears the previous one's wall by 0.6 mm."""
    H = air.H
    t_u, R_u = p["uncinate_thickness_mm"], p["uncinate_radius_mm"]
    y_u = air.mt_start + p["uncinate_y_offset_mm"]
    z_u = p["uncinate_z_frac"] * H
    c_u = np.array([_wall_x(air, y_u, z_u) - p["uncinate_bulge_mm"] + R_u + t_u, y_u, z_u])
    infundibulum = SphereCell("infundibulum", tuple(c_u), R_u, t_u)

    r_b, t_b = p["bulla_radius_mm"], p["bulla_wall_mm"]
    z_b = p["bulla_z_frac"] * H
    x_b = _wall_x(air, y_u + 8.0, z_b) - p["bulla_bulge_mm"] + r_b + t_b
    sep = max(t_u, t_b) + 0.6
    need = R_u + r_b + sep
    dxz2 = (x_b - c_u[0]) ** 2 + (z_b - c_u[2]) ** 2
    y_b = y_u + math.sqrt(max(need**2 - dxz2, 0.0)) + 0.2
    c_b = np.array([_wall_x(air, y_b, z_b) - p["bulla_bulge_mm"] + r_b + t_b, y_b, z_b])
    bulla = SphereCell("ethmoid_bulla", tuple(c_b), r_b, t_b)

    R_p, t_p = p["posterior_ethmoid_radius_mm"], p["basal_lamella_mm"]
    z_p = z_b
    x_p = _wall_x(air, y_b + 8.0, z_p) - p["basal_bulge_mm"] + R_p + t_p
    sep = max(t_b, t_p) + 0.6
    need = r_b + R_p + sep
    y_p = y_b + math.sqrt(max(need**2 - (x_p - c_b[0]) ** 2, 0.0)) + 0.2
    c_p = np.array([_wall_x(air, y_p, z_p) - p["basal_bulge_mm"] + R_p + t_p, y_p, z_p])
    post = SphereCell("posterior_ethmoid", tuple(c_p), R_p, t_p)
    return infundibulum, bulla, post


def _maxillary_sinus(
    air: AirwayField, p: dict[str, float], targets: tuple[SphereCell, SphereCell, SphereCell]
) -> tuple[np.ndarray, np.ndarray]:
    """Centre and semi-axes (mm) of the maxillary sinus: an ellipsoid below the ethmoid
    cells, lateral to the airway, pushed down and laterally until it clears them; its
    ostium (a cylinder from the infundibulum's centre to the sinus's) must clear the
    bulla and the posterior ethmoid cell by 0.5 mm."""
    infundibulum, bulla, post = targets
    c_u = np.asarray(infundibulum.center_mm)
    R_u, t_u = infundibulum.radius_mm, infundibulum.wall_mm
    wob = p["wobble_mm"]
    z_top = c_u[2] + 0.15 * R_u
    z_bot = -4.0
    az = (z_top - z_bot) / 2.0
    axy = p["maxillary_volume_mm3"] / (4.0 / 3.0 * math.pi * az)
    ax = math.sqrt(axy / 1.45)
    ay = 1.45 * ax
    x_wall = max(air.x_low, air.x_mid)
    m_center = np.array(
        [x_wall + wob + p["maxillary_wall_mm"] + ax, c_u[1] + 0.35 * ay, z_bot + az]
    )
    m_axes = np.array([ax, ay, az])
    r_o = p["ostium_radius_mm"]
    # push the sinus down/laterally until it clears the ethmoid cells by their wall + 0.6 mm
    for _ in range(60):
        clash = any(
            _sphere_hits_ellipsoid(
                c.center_mm, c.radius_mm + c.wall_mm + 0.6 + 0.5, m_center, m_axes
            )
            for c in (bulla, post)
        )
        if not clash:
            break
        m_center = m_center + np.array([0.3, 0.0, -0.3])
    else:
        raise AnatomyError(
            "anatomy", "maxillary sinus cannot clear the ethmoid bulla; choose other parameters"
        )
    for cell in (bulla, post):
        gap = (
            _segment_distance(np.asarray(cell.center_mm), c_u, m_center)
            - cell.radius_mm
            - r_o
            - max(cell.wall_mm, t_u)
        )
        if gap < 0.5:
            raise AnatomyError(
                "anatomy",
                f"maxillary ostium passes {gap:.2f} mm from the {cell.name} (expected >= 0.5 mm); choose other parameters",
            )
    return m_center, m_axes


def _ethmoid_cells(
    air: AirwayField,
    p: dict[str, float],
    seed: int,
    targets: tuple[SphereCell, SphereCell, SphereCell],
    m_center: np.ndarray,
    m_axes: np.ndarray,
) -> list[SphereCell]:
    """The further ethmoid cells, rejection-sampled above the maxillary sinus: each clears
    every cell placed before it, the sinus and the ostium by the thicker wall + 0.6 mm."""
    H = air.H
    infundibulum, _, post = targets
    c_u = np.asarray(infundibulum.center_mm)
    t_u = infundibulum.wall_mm
    r_o = p["ostium_radius_mm"]
    rng = np.random.default_rng([int(seed), 0xCE11])
    wall_e = p["ethmoid_cell_wall_mm"]
    n_eth = int(p["ethmoid_cells"])
    cells: list[SphereCell] = list(targets)
    placed = 0
    for attempt in range(1500):
        if placed == n_eth:
            break
        # smaller cells once the roomy spots are taken
        r = float(rng.uniform(2.5, 4.5) if attempt < 500 else rng.uniform(2.0, 3.0))
        y = float(rng.uniform(c_u[1] - 4.0, post.center_mm[1] + post.radius_mm + 4.0))
        z = float(rng.uniform(0.6 * H, 0.92 * H))
        x = _wall_x(air, y, z) + float(rng.uniform(1.0, 12.0)) + r
        c = np.array([x, y, z])
        ok = z + r + wall_e < H + 2.0
        for other in cells:
            d = float(np.linalg.norm(c - np.asarray(other.center_mm)))
            ok = ok and d >= r + other.radius_mm + max(wall_e, other.wall_mm) + 0.6
        ok = ok and not _sphere_hits_ellipsoid(c, r + wall_e + 0.6 + 0.5, m_center, m_axes)
        ok = ok and _segment_distance(c, c_u, m_center) >= r + r_o + max(wall_e, t_u) + 0.6
        if ok:
            placed += 1
            cells.append(SphereCell(f"ethmoid_cell_{placed}", (x, y, z), r, wall_e))
    if placed < n_eth:
        raise AnatomyError(
            "ethmoid_cells", f"could place only {placed} of {n_eth} ethmoid cells; choose fewer"
        )
    return cells[len(targets) :]


def _tissue_solid(
    air: AirwayField,
    p: dict[str, float],
    cells: list[SphereCell],
    m_center: np.ndarray,
    m_axes: np.ndarray,
    edge_mm: float,
) -> tuple[m3d.Manifold, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``block - (airway - walls) - voids`` as a manifold.

    Returns the tissue, the maxillary void's volume (mm^3), the block's corners and the
    airway's bounding box after the walls are taken out of it (mm)."""
    lo, hi = air.bounds()
    # an odd grid offset keeps marching-cubes vertices off the CT grid's lattice
    airway = drop_air_pockets(mesh_field(air, lo + 0.0731, hi, airway_grid_mm(edge_mm, p)))

    maxillary = m3d.Manifold.sphere(1.0, _segments(max(m_axes), max(edge_mm, 0.8))).scale(
        tuple(m_axes)
    )
    m_wall = m3d.Manifold.sphere(1.0, _segments(max(m_axes), max(edge_mm, 0.8))).scale(
        tuple(m_axes + p["maxillary_wall_mm"] + 0.5)
    )
    maxillary = maxillary.translate(tuple(m_center))
    m_wall = m_wall.translate(tuple(m_center))
    maxillary_volume = maxillary.volume()

    infundibulum = cells[0]
    c_u = np.asarray(infundibulum.center_mm)
    r_o, t_u = p["ostium_radius_mm"], infundibulum.wall_mm
    axis = m_center - c_u
    length = float(np.linalg.norm(axis))
    ostium = _cylinder(c_u, axis / length, length, r_o, edge_mm)
    ostium_wall = _cylinder(c_u, axis / length, length, r_o + t_u, edge_mm)

    walls = [sphere(c.center_mm, c.outer_radius_mm, edge_mm) for c in cells] + [m_wall, ostium_wall]
    voids = [sphere(c.center_mm, c.radius_mm, edge_mm) for c in cells] + [maxillary, ostium]
    airway = airway - m3d.Manifold.batch_boolean(walls, m3d.OpType.Add)
    box = airway.bounding_box()
    air_lo, air_hi = np.asarray(box[:3]), np.asarray(box[3:])

    b_lo, b_hi = _block_box(cells, m_center, m_axes, air.L, air.H)
    block = m3d.Manifold.cube(tuple(b_hi - b_lo)).translate(tuple(b_lo))
    tissue = block - airway - m3d.Manifold.batch_boolean(voids, m3d.OpType.Add)
    if tissue.status() != m3d.Error.NoError or tissue.is_empty():  # pragma: no cover
        raise AnatomyError("anatomy", f"tissue boolean failed: {tissue.status().name}")
    return tissue, maxillary_volume, b_lo, b_hi, air_lo, air_hi


def _block_box(
    cells: list[SphereCell], m_center: np.ndarray, m_axes: np.ndarray, L: float, H: float
) -> tuple[np.ndarray, np.ndarray]:
    """Corners of the tissue block, mm (rounded to 0.1 mm): 3 mm around every wall and the
    sinus, the airway's length and height + 4 mm; its medial face is the septum's midline
    and its anterior face the nostril's plane (y = 0)."""
    extents_lo = [np.asarray(c.center_mm) - c.outer_radius_mm for c in cells] + [
        m_center - m_axes - 2.0
    ]
    extents_hi = [np.asarray(c.center_mm) + c.outer_radius_mm for c in cells] + [
        m_center + m_axes + 2.0
    ]
    b_lo = np.minimum(np.min(extents_lo, axis=0) - 3.0, [_SEPTUM_FACE_X, 0.0, -4.0])
    b_hi = np.maximum(np.max(extents_hi, axis=0) + 3.0, [0.0, L + 4.0, H + 4.0])
    b_lo[0], b_lo[1] = _SEPTUM_FACE_X, 0.0
    return np.round(b_lo, 1), np.round(b_hi, 1)


def _nostril(air: AirwayField, p: dict[str, float]) -> tuple[float, float, float]:
    """Centre of the nostril on the block's anterior face (y = 0): midway between septum
    and lateral wall, midway between the sill and the vestibule's roof, mm."""
    z_nostril = 0.5 * (2.0 + p["vestibule_height_mm"])
    x_nostril = 0.5 * float(
        air.septum_x(np.array(0.0), np.array(z_nostril))
        + air.lateral_x(np.array(0.0), np.array(z_nostril))
    )
    return (x_nostril, 0.0, z_nostril)


def _cylinder(
    origin: np.ndarray, direction: np.ndarray, length: float, radius: float, edge_mm: float
) -> m3d.Manifold:
    """Cylinder of ``radius`` from ``origin`` along unit ``direction`` for ``length`` mm."""
    cyl = m3d.Manifold.cylinder(length, radius, radius, _segments(radius, edge_mm))
    return cyl.transform(_frame_z(origin, direction))


def _frame_z(origin: np.ndarray, z_axis: np.ndarray) -> list[list[float]]:
    """3x4 affine whose local +z is ``z_axis`` and whose origin is ``origin``."""
    z = np.asarray(z_axis, float) / np.linalg.norm(z_axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1)
    return np.concatenate([R, np.asarray(origin, float)[:, None]], axis=1).tolist()


def _count_shells(man: m3d.Manifold) -> int:
    """Number of connected surface shells (outer boundary + one per closed void)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    _, f = arrays_from_manifold(man)
    n = int(f.max()) + 1
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0]])
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    count, _ = connected_components(graph, directed=False)
    return int(count)
