"""Rigid surgical instruments in view: closed tool meshes in mm and collision-free tracks.

Tool frame (mm): the tip at the origin, the instrument's axis along +z (the direction it
advances), the shaft running back along -z; jaws open in the tool's x-z plane.

- :func:`tool_mesh` builds the built-in instruments from trimesh primitives joined with
  manifold3d booleans (closed, watertight): through-cutting/Blakesley forceps (two
  jaws, 3-5 mm wide, on a 2-3 mm shaft), a suction cannula (2-4 mm tube, open bevelled
  end) and a microdebrider (3-4 mm tube with a rounded end and a side cutting window).
- :func:`check_tool_mesh` refuses a tool model that is not closed or not in mm.
- :func:`plan_tool_track` draws, for one intraoperative sequence, episodes in which one
  instrument, held beside the scope on an axis that enters the view from the image edge,
  advances into view, works and withdraws; every frame's tool keeps
  ``tools.clearance_mm`` from tissue (:class:`sim.collision.TissueDistance`) and from
  the scope, else the episode is redrawn, split and at last dropped
  (:class:`~sim.errors.PathError` when fewer than half the frames asked for get a tool
  within ``tools.max_tries``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from chisel.core.geometry import Camera, make_transform
from chisel.io.meshfile import READABLE_MESH_SUFFIXES, read_mesh_file
from sim.collision import TissueDistance
from sim.config import ToolKind, ToolsConfig
from sim.errors import MeshError, PathError, PathInTissueError

log = logging.getLogger(__name__)

TOOL_KINDS: tuple[ToolKind, ...] = ("forceps", "suction", "microdebrider")
"""The built-in instruments, in the order of their index in a :class:`ToolTrack`."""
SCOPE_RADIUS_MM = 2.0
"""Radius of the endoscope's shaft (4 mm scope): a tool keeps out of it."""
CHECK_BEHIND_LENS_MM = 1.0
"""The tool is checked against tissue from its tip back to this far behind the lens plane.
Further back the shaft follows the scope's own corridor through the nostril and never
shows: every camera ray, shadow ray and depth ray runs in front of the lens plane (the
light sits in it), so no image, depth or mask depends on it."""
SAMPLE_AREA_MM2 = 0.1
"""Surface area per collision sample of a tool, mm^2."""
TOOL_LENGTH_RANGE_MM = (5.0, 400.0)
"""Accepted length of a tool model along its axis, mm (metres or inches fall outside)."""
TOOL_WIDTH_RANGE_MM = (0.5, 15.0)
"""Accepted width of a tool model across its axis, mm."""


def _cylinder(radius_mm: float, z0: float, z1: float, sections: int = 32) -> trimesh.Trimesh:
    c = trimesh.creation.cylinder(radius=radius_mm, height=z1 - z0, sections=sections)
    c.apply_translation([0.0, 0.0, 0.5 * (z0 + z1)])
    return c


def _union(parts: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    return trimesh.boolean.union(parts, engine="manifold")


def tool_mesh(kind: ToolKind, size_mm: float, shaft_mm: float, length_mm: float) -> trimesh.Trimesh:
    """A closed instrument mesh in the tool frame (tip at the origin, shaft along -z), mm.

    size_mm : jaw width (forceps) or outer diameter (suction, microdebrider), mm.
    shaft_mm : shaft diameter, mm (forceps; the others use ``size_mm``).
    length_mm : modelled length from the tip back, mm.
    """
    if kind == "forceps":
        jaw_len = 1.6 * size_mm + 2.0
        r_shaft = 0.5 * shaft_mm
        shaft = _cylinder(r_shaft, -length_mm, -jaw_len + 0.6)
        parts = [shaft]
        for side in (-1.0, 1.0):
            # A jaw: a capsule flattened to the jaw's width x 1 mm, opened 12 degrees.
            jaw = trimesh.creation.capsule(height=jaw_len - 0.5 * size_mm, radius=0.5 * size_mm)
            jaw.apply_scale([1.0, 1.0 / size_mm, 1.0])  # 1 mm thick
            jaw.apply_translation([0.0, 0.0, -0.5 * jaw_len])
            hinge = make_transform(
                trimesh.transformations.rotation_matrix(side * math.radians(12.0), [1, 0, 0])[
                    :3, :3
                ],
                [0.0, side * 0.3 * shaft_mm, -jaw_len + 0.3],
            )
            jaw.apply_translation([0.0, 0.0, jaw_len - 0.3])
            jaw.apply_transform(hinge)
            parts.append(jaw)
        mesh = _union(parts)
    elif kind == "suction":
        r = 0.5 * size_mm
        tube = _cylinder(r, -length_mm, 0.0)
        bore = _cylinder(0.6 * r, -4.0, 1.0)
        mesh = trimesh.boolean.difference([tube, bore], engine="manifold")
    elif kind == "microdebrider":
        r = 0.5 * size_mm
        body = _union([_cylinder(r, -length_mm, -r), _sphere(r, [0.0, 0.0, -r])])
        window = trimesh.creation.box(extents=[2.0 * r, 1.2 * r, 2.2 * r])
        window.apply_translation([r * 0.9, 0.0, -1.6 * r])
        mesh = trimesh.boolean.difference([body, window], engine="manifold")
    else:
        raise PathError("tools.kinds", f"unknown instrument {kind!r}; expected one of {TOOL_KINDS}")
    return check_tool_mesh(mesh, f"built-in {kind}")


def _sphere(radius_mm: float, center: list[float]) -> trimesh.Trimesh:
    s = trimesh.creation.icosphere(subdivisions=3, radius=radius_mm)
    s.apply_translation(center)
    return s


def check_tool_mesh(mesh: trimesh.Trimesh, source: str) -> trimesh.Trimesh:
    """Refuse a tool model that is not closed or not in mm; returns it.

    The length along the tool's z axis must lie in :data:`TOOL_LENGTH_RANGE_MM` and the
    width across it in :data:`TOOL_WIDTH_RANGE_MM` (a model in metres is ~0.03 long, one
    in micrometres 30,000): :class:`~sim.errors.MeshError` naming ``source``.
    """
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshError(source, "tool model is empty (no triangles)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(source, "tool model vertices contain NaN/inf")
    if not mesh.is_watertight:
        raise MeshError(
            source, "tool model is not closed (watertight): a solid instrument is needed"
        )
    ext = np.ptp(np.asarray(mesh.vertices), axis=0)
    length, width = float(ext[2]), float(max(ext[0], ext[1]))
    lo, hi = TOOL_LENGTH_RANGE_MM
    if not lo <= length <= hi:
        raise MeshError(
            source,
            f"tool model is {length:g} long along its axis (z), expected {lo:g}-{hi:g} mm: "
            "is it in mm, with the shaft along -z?",
        )
    lo, hi = TOOL_WIDTH_RANGE_MM
    if not lo <= width <= hi:
        raise MeshError(
            source,
            f"tool model is {width:g} wide across its axis, expected {lo:g}-{hi:g} mm: is it in mm?",
        )
    return mesh


def load_tool_model(path: str | Path) -> trimesh.Trimesh:
    """Read a user's tool model (``tools.model_file``); refused as in :func:`check_tool_mesh`."""
    p = Path(path)
    if not p.is_file():
        raise MeshError(p, "tools.model_file: file does not exist")
    mesh = read_mesh_file(
        p, "tools.model_file mesh", READABLE_MESH_SUFFIXES, process=True, error=MeshError
    )
    return check_tool_mesh(mesh, f"{p} (tools.model_file)")


@dataclass(frozen=True)
class ToolSet:
    """The instruments of one render: one mesh per kind (sizes drawn once per render)."""

    kinds: tuple[str, ...]
    """Instrument names, index = a :class:`ToolTrack`'s ``kind``."""
    meshes: tuple[trimesh.Trimesh, ...]
    """Closed meshes in the tool frame, mm."""
    sizes_mm: tuple[float, ...]
    """Jaw width or outer diameter of each, mm."""

    def samples(self, k: int) -> np.ndarray:
        """(M, 3) float64 points on tool ``k``'s surface, tool mm: its vertices plus seeded
        surface samples, one per :data:`SAMPLE_AREA_MM2` (~0.3 mm apart)."""
        m = self.meshes[k]
        count = int(np.ceil(m.area / SAMPLE_AREA_MM2))
        pts, _ = trimesh.sample.sample_surface(m, count, seed=k)
        return np.concatenate([m.vertices, pts])


def tool_set(cfg: ToolsConfig, seed: int) -> ToolSet:
    """The instruments of a render: ``cfg.model_file`` alone, or each of ``cfg.kinds`` with
    sizes drawn from their ranges (same seed, same meshes)."""
    if cfg.model_file is not None:
        mesh = load_tool_model(cfg.model_file)
        return ToolSet(("model",), (mesh,), (float(np.ptp(mesh.vertices[:, 0])),))
    rng = np.random.default_rng([int(seed), int(cfg.seed), 41])
    meshes, sizes = [], []
    for kind in cfg.kinds:
        if kind == "forceps":
            size = float(rng.uniform(*cfg.forceps_jaw_width_mm))
            shaft = float(rng.uniform(*cfg.forceps_shaft_mm))
        elif kind == "suction":
            size = shaft = float(rng.uniform(*cfg.suction_diameter_mm))
        else:
            size = shaft = float(rng.uniform(*cfg.microdebrider_diameter_mm))
        meshes.append(tool_mesh(kind, size, shaft, cfg.shaft_length_mm))
        sizes.append(size)
    return ToolSet(tuple(cfg.kinds), tuple(meshes), tuple(sizes))


@dataclass(frozen=True)
class ToolTrack:
    """Where the instrument is in each frame of a sequence."""

    kind: np.ndarray
    """(N,) int, index into the :class:`ToolSet` (-1 = no tool in this frame)."""
    T_world_from_tool: np.ndarray
    """(N, 4, 4) float64 tool poses, mm (identity where ``kind`` is -1)."""

    @staticmethod
    def empty(n: int) -> ToolTrack:
        return ToolTrack(np.full(n, -1, dtype=int), np.tile(np.eye(4), (n, 1, 1)))


def _frame_along(axis: np.ndarray, up: np.ndarray) -> np.ndarray:
    z = axis / np.linalg.norm(axis)
    x = np.cross(up, z)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def tool_clearance_mm(
    tools: ToolSet,
    track: ToolTrack,
    T_world_from_cam: np.ndarray,
    tissue: TissueDistance,
) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: the tool's smallest signed distance to tissue and to the scope's axis.

    Returns two (N,) float64 arrays in mm (inf where no tool): the minimum over the tool's
    surface samples in front of :data:`CHECK_BEHIND_LENS_MM` behind the lens plane of the
    tissue's signed distance (> 0 in air), and over all samples of the distance from
    the scope (the camera's optical axis behind the lens, and the lens itself) minus
    :data:`SCOPE_RADIUS_MM`.
    """
    n = len(track.kind)
    d_tissue = np.full(n, np.inf)
    d_scope = np.full(n, np.inf)
    for i in np.flatnonzero(track.kind >= 0):
        pts = tools.samples(int(track.kind[i]))
        T = track.T_world_from_tool[i]
        world = pts @ T[:3, :3].T + T[:3, 3]
        Tc = np.linalg.inv(T_world_from_cam[i])
        cam = world @ Tc[:3, :3].T + Tc[:3, 3]
        seen = cam[:, 2] >= -CHECK_BEHIND_LENS_MM
        if seen.any():
            d_tissue[i] = float(tissue.signed_distance(world[seen]).min())
        behind = np.hypot(cam[:, 0], cam[:, 1])
        radial = np.where(cam[:, 2] <= 0, behind, np.linalg.norm(cam, axis=1))
        d_scope[i] = float(radial.min()) - SCOPE_RADIUS_MM
    return d_tissue, d_scope


def check_tool_track(
    tools: ToolSet,
    track: ToolTrack,
    T_world_from_cam: np.ndarray,
    tissue: TissueDistance,
    clearance_mm: float,
    what: str = "tool path",
) -> None:
    """Raise :class:`~sim.errors.PathInTissueError` if a frame's tool enters tissue or the
    scope, :class:`~sim.errors.PathError` if it comes closer than ``clearance_mm``."""
    d_tissue, d_scope = tool_clearance_mm(tools, track, T_world_from_cam, tissue)
    bad = np.flatnonzero(d_tissue < 0)
    if len(bad):
        raise PathInTissueError(
            tissue.source,
            f"{what}: the tool is inside tissue in frame {int(bad[0])} "
            f"(signed distance {d_tissue[bad[0]]:.2f} mm)",
        )
    bad = np.flatnonzero(d_scope < 0)
    if len(bad):
        raise PathInTissueError(
            "tools", f"{what}: the tool passes through the scope in frame {int(bad[0])}"
        )
    bad = np.flatnonzero(d_tissue < clearance_mm)
    if len(bad):
        raise PathError(
            tissue.source,
            f"{what}: the tool comes {d_tissue[bad[0]]:.2f} mm from tissue in frame "
            f"{int(bad[0])}, less than tools.clearance_mm = {clearance_mm:g}",
        )


RELOCATE_TRIES = 4
"""Per sequence, how many times an episode that fits nowhere in its frames (even split)
is moved to other free frames before it is left out."""


def _episodes(n: int, cfg: ToolsConfig, rng: np.random.Generator) -> list[tuple[int, int]]:
    """Disjoint [start, end) frame ranges covering about ``fraction`` of ``n`` frames."""
    want = int(round(cfg.fraction * n))
    if want == 0:
        return []
    lo, hi = cfg.episode_frames
    lengths: list[int] = []
    while sum(lengths) < want:
        lengths.append(min(int(rng.integers(lo, hi + 1)), want - sum(lengths)))
    gaps = n - sum(lengths)
    # Random gaps before, between and after the episodes.
    cuts = np.sort(rng.integers(0, gaps + 1, size=len(lengths)))
    out, pos, used_gap = [], 0, 0
    for length, cut in zip(lengths, cuts, strict=True):
        pos += int(cut) - used_gap
        used_gap = int(cut)
        out.append((pos, pos + length))
        pos += length
    return out


def plan_tool_track(
    tools: ToolSet,
    camera: Camera,
    T_world_from_cam: np.ndarray,
    tissue: TissueDistance,
    cfg: ToolsConfig,
    seed: int,
) -> ToolTrack:
    """Tool poses for every frame of one sequence (see the module docstring).

    T_world_from_cam : (N, 4, 4) float64 true camera poses, mm. The instrument goes through
    the nostril beside the scope, so its pose is held relative to the camera (the surgeon
    moves both together): per episode, a side ``phi`` around the optical axis; the axis
    crosses the lens plane ``2 mm + tool radius + 0.3-1.2 mm`` from the optical centre
    towards ``phi`` and runs nearly parallel to the optical axis (converging by up to
    1.5 mm at the tip), so the shaft enters the view from its edge; the tip sits at a depth
    from ``cfg.tip_depth_mm`` (capped 1.5 mm in front of the tissue seen there in every
    frame of the episode). Over the first quarter of the episode the tool advances
    ``travel_mm`` along its axis, over the last it withdraws. Every frame is checked
    (:func:`tool_clearance_mm`); a failing episode is redrawn, and after ``cfg.max_tries``
    split in two (while both halves keep half of ``episode_frames``' minimum: a surgeon
    withdraws a tool early when the scope turns into a narrow passage); a piece that still
    fails is moved to other free frames (up to :data:`RELOCATE_TRIES` times per
    sequence), then left without a tool (a warning names its frames), and :class:`PathError`
    is raised when fewer than half of the frames asked for got one. Same inputs and seed,
    same track.
    """
    P = np.asarray(T_world_from_cam, dtype=np.float64).reshape(-1, 4, 4)
    n = len(P)
    rng = np.random.default_rng([int(seed), int(cfg.seed), 43])
    kind = np.full(n, -1, dtype=int)
    poses = np.tile(np.eye(4), (n, 1, 1))
    todo = _episodes(n, cfg, rng)
    want = sum(b - a for a, b in todo)
    dropped: list[tuple[int, int]] = []
    relocations = 0
    min_piece = max(1, (cfg.episode_frames[0] + 1) // 2)
    while todo:
        start, end = todo.pop(0)
        frames = np.arange(start, end)
        s = (frames - start + 0.5) / (end - start)
        ramp = np.clip(np.minimum(s, 1.0 - s) / 0.25, 0.0, 1.0)  # 0 -> 1 -> 0
        insertion = 0.5 - 0.5 * np.cos(np.pi * ramp)  # smooth in and out
        for _ in range(cfg.max_tries):
            k = int(rng.integers(len(tools.meshes)))
            radius = 0.5 * tools.sizes_mm[k]
            phi = float(rng.uniform(0.0, 2.0 * math.pi))
            side = np.array([math.cos(phi), math.sin(phi), 0.0])
            s0 = SCOPE_RADIUS_MM + radius + float(rng.uniform(0.3, 1.2))
            z_tip = float(rng.uniform(*cfg.tip_depth_mm))
            tip = side * (s0 - float(rng.uniform(0.0, 1.5))) + np.array([0.0, 0.0, z_tip])
            # Stay in front of the tissue seen through the tip, in every frame of the
            # episode (the scope moves towards tissue within one).
            o = P[frames, :3, 3]
            d_world = P[frames, :3, :3] @ (tip / np.linalg.norm(tip))
            t_hit = float(np.min(tissue.first_hit_mm(o, o + d_world)))
            z_cap = t_hit * tip[2] / np.linalg.norm(tip) - 1.5
            if z_cap < 2.0:
                continue
            if z_tip > z_cap:
                tip = tip * (z_cap / z_tip)
            axis = tip - s0 * side
            axis /= np.linalg.norm(axis)
            R_cam = _frame_along(axis, np.cross(np.array([0.0, 0.0, 1.0]), side))
            T_cam_from_tool = np.tile(make_transform(R_cam, tip), (len(frames), 1, 1))
            T_cam_from_tool[:, :3, 3] -= ((1.0 - insertion) * cfg.travel_mm)[:, None] * axis
            ep = P[frames] @ T_cam_from_tool
            cand = ToolTrack(np.full(len(frames), k), ep)
            d_t, d_s = tool_clearance_mm(tools, cand, P[frames], tissue)
            if d_t.min() >= cfg.clearance_mm and d_s.min() >= 0.0:
                kind[frames] = k
                poses[frames] = ep
                break
        else:
            if end - start >= 2 * min_piece:
                # The scope moves too far within a long episode for one rigid tool pose
                # beside it (a narrow passage): two shorter episodes, drawn afresh.
                half = start + (end - start) // 2
                todo[:0] = [(start, half), (half, end)]
                continue
            if relocations < RELOCATE_TRIES:
                # A narrow passage: the surgeon brings the tool in at another moment, in
                # frames that hold no tool and no planned episode.
                relocations += 1
                free = np.ones(n, dtype=bool)
                free[kind >= 0] = False
                for a, b in [*todo, (start, end)]:
                    free[a:b] = False
                length = end - start
                ok = np.convolve(free.astype(int), np.ones(length, dtype=int), "valid") == length
                if ok.any():
                    new_start = int(rng.choice(np.flatnonzero(ok)))
                    todo.append((new_start, new_start + length))
                    continue
            dropped.append((start, end))
    if dropped:
        ranges = ", ".join(f"{a}-{b - 1}" for a, b in dropped)
        placed = int((kind >= 0).sum())
        if placed < 0.5 * want:
            raise PathError(
                "tools.max_tries",
                f"no tool episode clear of tissue in {cfg.max_tries} tries (frames {ranges}; "
                f"tools in {placed} of the {want} frames asked for; tissue mesh "
                f"{tissue.source}): lower tools.tip_depth_mm, tools.clearance_mm, "
                "tools.shaft_length_mm or tools.fraction",
            )
        log.warning(
            "tools: no episode clear of tissue in frames %s of %s (a narrow passage); "
            "tools in %d of the %d frames asked for",
            ranges,
            tissue.source,
            placed,
            want,
        )
    return ToolTrack(kind, poses)
