"""Mitsuba 3 endoscope renderer: one scene per tissue mesh, poses updated per frame.

A :class:`MeshRenderer` loads one mesh into one Mitsuba scene (principled BSDF over the
procedural 3D texture, a spot light at the scope tip, a perspective sensor on the
undistorted :class:`~sim.mitsuba_camera.RenderGrid`) and then only updates poses per
frame, so drjit reuses its compiled kernels.

Per frame it returns RGB (direct lighting, ``spp`` samples, then the sensor model of
:mod:`sim.imaging`), z-depth in mm and the validity mask. On the JIT variants colour is
traced by :class:`~sim.spot_direct.SpotDirectIntegrator` along the exact rays of the raw
pixels inside the field stop, and depth is Mitsuba's ray intersection along the exact
ray of every raw pixel centre (both exact under distortion); :meth:`MeshRenderer.render`
evaluates depth, colour and the sensor model (in drjit) in one launch. On ``scalar_rgb`` colour is
``mi.render`` with Mitsuba's ``direct`` integrator on the render grid, remapped onto the
raw grid, and depth the sensor's ``depth`` AOV at pixel centres, remapped with nearest
neighbour; :meth:`MeshRenderer.render_radiance_reference` keeps that path on every
variant as the reference the fast one is tested against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from chisel.core.geometry import check_rigid, make_transform
from chisel.core.mitsuba_variant import load_mitsuba
from chisel.core.raycast import jit_z_depth, unit_rays
from sim.appearance import TextureVolume
from sim.config import SimConfig
from sim.imaging import field_stop_mask, sensor_image, vignetting_gain
from sim.mitsuba_camera import (
    RenderGrid,
    mitsuba_to_world,
    remap_to_camera,
    render_grid,
    z_depth_from_mitsuba_depth,
)
from sim.phantom import check_mesh
from sim.spot_direct import SpotDirectIntegrator


@dataclass(frozen=True)
class RenderedFrame:
    """One rendered frame in memory."""

    depth_mm: np.ndarray
    """(H, W) float32 z-depth in mm, NaN where the ray misses the tissue."""
    valid: np.ndarray
    """(H, W) bool, True where the depth is valid."""
    rgb: np.ndarray | None = None
    """(H, W, 3) uint8 RGB, None in depth-only mode."""


def _frame_seed(seed: int, index: int) -> int:
    return (int(seed) * 1_000_003 + int(index) * 7_919 + 17) % (2**32)


def _noise_key(seed: int, index: int) -> int:
    """Sensor-noise key of a frame, unrelated to its Monte Carlo sampler seed."""
    return (_frame_seed(seed, index) * 2_654_435_761 + 0x5E45) % (2**32)


class MeshRenderer:
    """Render one tissue mesh from arbitrary camera poses.

    mesh : closed trimesh, world mm (checked: non-empty, finite, watertight).
    cfg : the simulator configuration (camera, light, appearance, imaging).
    texture : the baked colour volume; required unless ``depth_only``.
    depth_only : build a geometry-only scene (no BSDF texture, light or RGB).
    """

    def __init__(
        self,
        mesh: trimesh.Trimesh,
        cfg: SimConfig,
        texture: TextureVolume | None = None,
        depth_only: bool = False,
    ) -> None:
        check_mesh(mesh, "mesh")
        self.cfg = cfg
        self.depth_only = bool(depth_only)
        if not self.depth_only and texture is None:
            raise ValueError("MeshRenderer: a texture volume is required to render RGB")
        self.mi, self.variant = load_mitsuba(cfg.variant)
        mi = self.mi
        import drjit  # noqa: PLC0415 - only after mitsuba picked the variant

        self.drjit = drjit
        mi.set_log_level(mi.LogLevel.Warn)
        self.jit = self.variant != "scalar_rgb"
        self.camera = cfg.camera.camera()
        self.field_stop = field_stop_mask(cfg.camera)
        # Colour only matters inside the field stop: the render grid covers just those rays.
        self.grid = render_grid(self.camera, cfg.camera.max_render_upscale, used=self.field_stop)
        self._gain = vignetting_gain(cfg.camera)
        dirs = unit_rays(self.camera.rays_cam())
        # Unit ray directions of every raw pixel (camera frame), uploaded once; per frame
        # only the poses travel to drjit and rays are built by gathers (no recompilation).
        self._dirs_cam = (
            mi.Vector3f(np.ascontiguousarray(dirs.reshape(-1, 3).T)) if self.jit else None
        )

        props = mi.Properties()
        if not self.depth_only:
            assert texture is not None
            box = texture.box_mm
            to_world = make_transform(np.diag(box[1] - box[0]), box[0])
            bsdf = mi.load_dict(
                {
                    "type": "principled",
                    "base_color": {
                        "type": "volume",
                        "volume": {
                            "type": "gridvolume",
                            "grid": mi.VolumeGrid(
                                np.ascontiguousarray(texture.rgb, dtype=np.float32)
                            ),
                            "to_world": mi.ScalarTransform4f(to_world),
                        },
                    },
                    "roughness": float(cfg.appearance.roughness),
                    "specular": float(cfg.appearance.specular),
                }
            )
            props["bsdf"] = bsdf
        self.mesh = mi.Mesh(
            "tissue",
            len(mesh.vertices),
            len(mesh.faces),
            props=props,
            has_vertex_normals=not self.depth_only,
        )
        mp = mi.traverse(self.mesh)
        mp["vertex_positions"] = np.ascontiguousarray(
            np.asarray(mesh.vertices, dtype=np.float32).ravel()
        )
        mp["faces"] = np.ascontiguousarray(np.asarray(mesh.faces, dtype=np.uint32).ravel())
        mp.update()
        if not self.depth_only:
            self.mesh.recompute_vertex_normals()

        spp = int(cfg.imaging.spp)
        square = int(round(spp**0.5)) ** 2 == spp
        scene: dict = {"type": "scene", "tissue": self.mesh}
        if not self.depth_only:
            scene["integrator"] = {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}
            scene["sensor"] = self._sensor_dict(
                {"type": "stratified", "sample_count": spp}
                if square
                else {"type": "independent", "sample_count": spp},
                "rgb",
            )
            lc = cfg.light
            scene["light"] = {
                "type": "spot",
                "intensity": {"type": "rgb", "value": float(lc.intensity)},
                "cutoff_angle": float(lc.cutoff_deg),
                "beam_width": float(lc.beam_width_deg),
            }
        self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)
        self._T_cam_from_light = make_transform(
            np.eye(3), np.asarray(cfg.light.offset_mm, dtype=np.float64)
        )
        self._depth_sensor = None
        self._direct = None
        if self.jit and not self.depth_only:
            assert texture is not None
            self._direct = SpotDirectIntegrator(
                mi,
                self.scene,
                self.camera,
                self.field_stop,
                cfg.light,
                spp,
                texture,
                roughness=float(cfg.appearance.roughness),
                specular=float(cfg.appearance.specular),
            )
            self._gain_used = mi.Float(self._gain.ravel()[self.field_stop.ravel()])

    def _sensor_dict(
        self, sampler: dict, pixel_format: str, grid: RenderGrid | None = None
    ) -> dict:
        g = self.grid if grid is None else grid
        ppo_x, ppo_y = g.principal_point_offset()
        return {
            "type": "perspective",
            "fov": g.x_fov_deg(),
            "fov_axis": "x",
            "principal_point_offset_x": ppo_x,
            "principal_point_offset_y": ppo_y,
            "near_clip": float(self.cfg.camera.near_clip_mm),
            "far_clip": 1.0e5,
            "film": {
                "type": "hdrfilm",
                "width": g.width,
                "height": g.height,
                "rfilter": {"type": "box"},
                "pixel_format": pixel_format,
            },
            "sampler": sampler,
        }

    # -- depth ---------------------------------------------------------------------------

    def render_depth(self, poses: np.ndarray) -> np.ndarray:
        """z-depth maps for a batch of poses.

        poses : (N, 4, 4) or (4, 4) float64 ``T_world_from_cam``, mm (OpenCV axes).
        Returns (N, H, W) float32 z-depth in mm, NaN on a miss.
        """
        T = check_rigid(poses, "T_world_from_cam").reshape(-1, 4, 4)
        if not self.jit:
            return np.stack([self._depth_via_sensor(t) for t in T])
        z = jit_z_depth(self.mi, self.scene, self._dirs_cam, T)
        return np.array(z, dtype=np.float32).reshape(len(T), *self.camera.shape)

    def _depth_via_sensor(self, T_world_from_cam: np.ndarray) -> np.ndarray:
        """Depth from the sensor's ``depth`` AOV (scalar_rgb has no vectorised ray queries).

        A 1-spp stratified sampler without jitter puts the one sample at the pixel centre;
        the near-plane ray length is converted to z-depth on the render grid, then remapped
        onto the raw pixel grid with nearest neighbour.
        """
        mi = self.mi
        if self._depth_sensor is None:
            # Depth is needed at every pixel, not just inside the field stop: a full grid.
            self._depth_grid = render_grid(self.camera, self.cfg.camera.max_render_upscale)
            self._depth_sensor = mi.load_dict(
                self._sensor_dict(
                    {"type": "stratified", "sample_count": 1, "jitter": False},
                    "luminance",
                    self._depth_grid,
                )
            )
            self._depth_sensor_params = mi.traverse(self._depth_sensor)
            self._depth_integrator = mi.load_dict({"type": "aov", "aovs": "dd:depth"})
        self._depth_sensor_params["to_world"] = mi.ScalarTransform4f(
            mitsuba_to_world(T_world_from_cam)
        )
        self._depth_sensor_params.update()
        img = mi.render(
            self.scene, sensor=self._depth_sensor, integrator=self._depth_integrator, spp=1
        )
        aov = np.array(img, dtype=np.float32)[..., -1]
        z_grid = z_depth_from_mitsuba_depth(aov, self._depth_grid, self.cfg.camera.near_clip_mm)
        z = remap_to_camera(np.nan_to_num(z_grid, nan=0.0), self._depth_grid, nearest=True)
        return np.where(z > 0, z, np.nan).astype(np.float32)

    # -- colour --------------------------------------------------------------------------

    def render_radiance(self, T_world_from_cam: np.ndarray, seed: int = 0) -> np.ndarray:
        """Linear radiance on the raw camera grid, before the sensor model.

        T_world_from_cam : (4, 4) float64, mm. Returns (H, W, 3) float32 (0 outside the
        field stop on the JIT variants).
        """
        if self.depth_only:
            raise ValueError("MeshRenderer: built with depth_only=True, cannot render RGB")
        T = check_rigid(T_world_from_cam, "T_world_from_cam")
        if self._direct is None:
            return self.render_radiance_reference(T, seed)
        return self._direct.render(T, seed=int(seed))

    def primary_hit_mm(self, T_world_from_cam: np.ndarray, seed: int = 0) -> np.ndarray:
        """Distance along each colour sample's primary ray to the first surface, alone.

        The part of :meth:`render_radiance` no shading or shadow work can remove, so its
        time bounds the RGB frame rate on a host (``benchmarks/bench_render.py``).
        T_world_from_cam : (4, 4) float64, mm. Returns (n_used_pixels, spp) float32 mm,
        inf on a miss; the used pixels in row-major order. JIT variants only.
        """
        if self._direct is None:
            raise ValueError(
                f"MeshRenderer: the primary rays alone need a JIT variant and RGB "
                f"(variant {self.variant}, depth_only={self.depth_only})"
            )
        T = check_rigid(T_world_from_cam, "T_world_from_cam")
        t = np.asarray(self._direct.primary_hit_mm(T, seed=int(seed)), dtype=np.float32)
        return t.reshape(self._direct.n_pixels, self._direct.spp)

    def render_radiance_reference(self, T_world_from_cam: np.ndarray, seed: int = 0) -> np.ndarray:
        """Radiance from ``mi.render`` with Mitsuba's ``direct`` integrator (the reference).

        Rendered on the undistorted render grid and remapped (bilinear) onto the raw grid.
        T_world_from_cam : (4, 4) float64, mm. Returns (H, W, 3) float32.
        """
        if self.depth_only:
            raise ValueError("MeshRenderer: built with depth_only=True, cannot render RGB")
        mi = self.mi
        T = check_rigid(T_world_from_cam, "T_world_from_cam")
        self.params["sensor.to_world"] = mi.ScalarTransform4f(mitsuba_to_world(T))
        self.params["light.to_world"] = mi.ScalarTransform4f(T @ self._T_cam_from_light)
        self.params.update()
        img = mi.render(
            self.scene, params=self.params, spp=int(self.cfg.imaging.spp), seed=int(seed)
        )
        rad = np.array(img, dtype=np.float32)[..., :3]
        return remap_to_camera(rad, self.grid, nearest=False)

    def render(self, T_world_from_cam: np.ndarray, index: int = 0, seed: int = 0) -> RenderedFrame:
        """Depth, validity and (unless depth-only) RGB of one frame.

        T_world_from_cam : (4, 4) float64 true pose, mm. ``index`` and ``seed`` seed the
        Monte Carlo sampler and the sensor noise (same seed and index -> same bytes).
        """
        T = check_rigid(T_world_from_cam, "T_world_from_cam")
        if self._direct is not None:
            return self._render_jit(T, index, seed)
        depth = self.render_depth(T)[0]
        valid = np.isfinite(depth)
        rgb = None
        if not self.depth_only:
            fs = _frame_seed(seed, index)
            rad = self.render_radiance(T_world_from_cam, seed=fs)
            rgb = sensor_image(
                rad, self._gain, self.cfg.imaging, np.random.default_rng([int(seed), int(index), 5])
            )
        return RenderedFrame(depth_mm=depth, valid=valid, rgb=rgb)

    def _render_jit(self, T: np.ndarray, index: int, seed: int) -> RenderedFrame:
        """RGB-D on the JIT variants: one launch for the depth rays, colour and sensor.

        The depth rays (every raw pixel centre, exact) are scheduled with the colour rays
        of the field-stop pixels and evaluated in the same launch; the sensor model runs
        in drjit on the used pixels (only the auto-exposure mean is a separate reduction),
        whose 8-bit RGB is packed into one 32-bit word and scattered into the full frame
        there too, so the host only copies the results out.
        """
        assert self._direct is not None
        dr, mi = self.drjit, self.mi
        H, W = self.camera.shape
        z = jit_z_depth(mi, self.scene, self._dirs_cam, T[None])
        dr.schedule(z)
        rad = self._direct.radiance(T, seed=_frame_seed(seed, index))
        q = self._direct.sensor(rad, self._gain_used, self.cfg.imaging, _noise_key(seed, index))
        rgbx = dr.zeros(mi.UInt32, H * W)
        dr.scatter(rgbx, q.x | (q.y << 8) | (q.z << 16), self._direct.used_index)
        dr.eval(z, rgbx)
        depth = np.array(z, dtype=np.float32).reshape(H, W)
        # Bytes r, g, b, 0 of each little-endian word: an (H, W, 4) view, alpha dropped.
        rgb = (
            np.asarray(rgbx, dtype=np.uint32)
            .astype("<u4", copy=False)
            .view(np.uint8)
            .reshape(H, W, 4)
        )
        return RenderedFrame(
            depth_mm=depth, valid=np.isfinite(depth), rgb=np.ascontiguousarray(rgb[..., :3])
        )
