"""A small synthetic endoscopy scene exported in *foreign* formats, for the importer tests.

The scene: the camera inside a closed sphere (every ray hits), a procedural texture on
the wall, a headlight, a distorting lens and a black field stop around a circle. Its
truth (poses, raw depth, pinhole renders) is computed here with the project's own ray
caster, independently of the importer's remap. Other test modules import from here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from chisel.core.geometry import Camera, invert_rigid, look_at, make_transform
from chisel.core.raycast import MeshRaycaster
from chisel.io.undistort import Circle, circle_mask

SPHERE_CENTRE_MM = np.array([12.0, -7.0, 60.0])
SPHERE_RADIUS_MM = 30.0
RAW_CAMERA = Camera.from_fov(
    96,
    80,
    100.0,
    principal_offset_px=(0.6, -0.4),
    dist=np.array([-0.28, 0.07, 0.0015, -0.001, 0.0]),
)
FIELD_STOP = Circle(48.1, 39.2, 37.3)


@dataclass
class Scene:
    raycaster: MeshRaycaster
    poses: np.ndarray  # (N, 4, 4) T_world_from_cam, mm
    raw_rgb: list[np.ndarray]  # (H, W, 3) uint8, distorted, field stop applied
    raw_depth: list[np.ndarray]  # (H, W) float32 mm, NaN outside the field stop


def make_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = []
    for i in range(n):
        eye = (
            SPHERE_CENTRE_MM
            + np.array([-6.0 + 1.5 * i, 3.0 * np.sin(i), -8.0])
            + rng.normal(0, 0.3, 3)
        )
        target = SPHERE_CENTRE_MM + np.array([4.0 * np.cos(i), 2.0 * i - 6.0, 25.0])
        poses.append(look_at(eye, target, up=[0.0, -1.0, 0.2]))
    return np.stack(poses)


def shade(raycaster: MeshRaycaster, camera: Camera, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rgb uint8, z-depth float32 mm) of the sphere wall seen by ``camera`` at ``T``."""
    depth = raycaster.render_depth(camera, T)
    pts_cam = camera.rays_cam() * depth[..., None].astype(np.float64)
    pts = pts_cam @ T[:3, :3].T + T[:3, 3]
    normal = (SPHERE_CENTRE_MM - pts) / SPHERE_RADIUS_MM
    view = T[:3, 3] - pts
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    lambert = np.clip(np.sum(normal * view, axis=-1), 0.0, 1.0)
    tex = 0.5 + 0.5 * np.sin(0.45 * pts[..., 0]) * np.cos(0.38 * pts[..., 1] + 0.2 * pts[..., 2])
    base = np.stack([0.85 * tex + 0.15, 0.35 + 0.4 * tex, 0.3 + 0.2 * (1 - tex)], axis=-1)
    rgb = 255.0 * (0.35 + 0.65 * lambert)[..., None] * base
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8), depth


def make_scene(n: int = 6, seed: int = 0) -> Scene:
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=SPHERE_RADIUS_MM)
    mesh.apply_translation(SPHERE_CENTRE_MM)
    raycaster = MeshRaycaster.from_trimesh(mesh)
    poses = make_poses(n, seed)
    stop = circle_mask(RAW_CAMERA.shape, FIELD_STOP)
    rgbs, depths = [], []
    for T in poses:
        rgb, depth = shade(raycaster, RAW_CAMERA, T)
        rgb[~stop] = 0
        depth = depth.copy()
        depth[~stop] = np.nan
        rgbs.append(rgb)
        depths.append(depth)
    return Scene(raycaster, poses, rgbs, depths)


# ------------------------------------------------------------------ foreign-format writers


def write_tum(path: Path, times_s: np.ndarray, poses: np.ndarray, scale: float = 1.0) -> None:
    """TUM trajectory: ``t tx ty tz qx qy qz qw``; translations multiplied by ``scale``."""
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, T in zip(times_s, poses, strict=True):
        if not np.isfinite(T).all():
            lines.append(f"{t:.9f} nan nan nan nan nan nan nan")
            continue
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        vals = [*(T[:3, 3] * scale), *q]
        lines.append(f"{t:.9f} " + " ".join(f"{v:.17g}" for v in vals))
    path.write_text("\n".join(lines) + "\n")


def write_matrix_rows(path: Path, poses: np.ndarray, scale: float = 1.0) -> None:
    P = poses.copy()
    P[:, :3, 3] *= scale
    path.write_text("\n".join(" ".join(f"{v:.17g}" for v in T.ravel()) for T in P) + "\n")


def write_video(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> None:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert writer.isOpened()
    for f in frames:
        writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    writer.release()


def write_images(
    folder: Path, frames: list[np.ndarray], ext: str = "png", prefix: str = "frame_"
) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, f in enumerate(frames):
        p = folder / f"{prefix}{i}.{ext}"  # unpadded on purpose: natural order must hold
        cv2.imwrite(str(p), cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
        paths.append(p)
    return paths


def tracker_poses(
    poses: np.ndarray, T_world_from_tracker: np.ndarray, T_marker_from_cam: np.ndarray
) -> np.ndarray:
    """What a tracker would report: T_tracker_from_marker for each T_world_from_cam."""
    return invert_rigid(T_world_from_tracker) @ poses @ invert_rigid(T_marker_from_cam)


HAND_EYE = make_transform(
    Rotation.from_euler("xyz", [10, -20, 5], degrees=True).as_matrix(), [3.0, -40.0, 12.0]
)
WORLD_FROM_TRACKER = make_transform(
    Rotation.from_euler("zyx", [30, 5, -60], degrees=True).as_matrix(), [250.0, -120.0, 900.0]
)


def test_scene_sees_the_wall_everywhere() -> None:
    scene = make_scene(2)
    stop = circle_mask(RAW_CAMERA.shape, FIELD_STOP)
    for rgb, depth in zip(scene.raw_rgb, scene.raw_depth, strict=True):
        assert np.isfinite(depth[stop]).all() and np.all(depth[stop] > 1.0)
        assert rgb[stop].min() > 0 and rgb[~stop].max() == 0
