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
from typing import Any

import numpy as np
import trimesh

from chisel.core.geometry import check_rigid, make_transform
from chisel.core.mitsuba_variant import deterministic_build, load_mitsuba
from chisel.core.raycast import jit_z_depth, unit_rays
from sim.appearance import TextureVolume
from sim.config import SimConfig
from sim.effects import FrameEffects, apply_effects, blur_poses
from sim.imaging import field_stop_mask, sensor_image, vignetting_gain
from sim.materials import SharedMaterials, steel_dict
from sim.mitsuba_camera import (
    RenderGrid,
    mitsuba_to_world,
    remap_to_camera,
    render_grid,
    z_depth_from_mitsuba_depth,
)
from sim.phantom import check_mesh
from sim.spot_direct import SpotDirectIntegrator
from sim.tools import ToolSet


@dataclass(frozen=True)
class RenderedFrame:
    """One rendered frame in memory."""

    depth_mm: np.ndarray
    """(H, W) float32 z-depth in mm, NaN where the ray misses the tissue."""
    valid: np.ndarray
    """(H, W) bool, True where the depth is valid."""
    rgb: np.ndarray | None = None
    """(H, W, 3) uint8 RGB, None in depth-only mode."""
    depth_visible_mm: np.ndarray | None = None
    """(H, W) float32 z-depth in mm of the visible scene (instruments included), NaN on a
    miss; None when the renderer has no instruments (then it equals ``depth_mm``)."""
    tool_mask: np.ndarray | None = None
    """(H, W) bool, True where the pixel centre's first hit is an instrument; None when the
    renderer has no instruments."""


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
    cut_faces : optional (F,) bool per face of ``mesh``, True = a face a cut created; those
        faces render with ``cut_texture`` as base colour (Mitsuba: a ``blendbsdf`` whose
        weight is the ``face_cut`` mesh attribute; the fast integrator gathers the same
        label). All False or None: one material, as before.
    blood_weight : optional (F,) float blood-film coverage in [0, 1] per face of ``mesh``
        (:func:`sim.blood.blood_film_weight`); the faces' BSDF is blended with
        ``cfg.blood``'s (Mitsuba: a ``blendbsdf`` over the ``face_blood`` mesh attribute;
        the fast integrator gathers the same weight). All 0 or None: no film, the same
        bytes as before.
    shared : optional :class:`~sim.materials.SharedMaterials` of the other renderers of the same
        phantom (same textures, appearance and blood config): the same bytes, less set-up.
    tools : optional instruments (one Mitsuba mesh each: ``roughconductor`` blended with
        ``tools.diffuse`` of a grey ``diffuse``, brushed steel), placed per
        frame with :meth:`place_tool`; frames then also return the visible depth and the
        tool mask, and ``depth_mm`` stays the tissue's (a tissue-only scene traces it).
    """

    def __init__(
        self,
        mesh: trimesh.Trimesh,
        cfg: SimConfig,
        texture: TextureVolume | None = None,
        depth_only: bool = False,
        cut_faces: np.ndarray | None = None,
        cut_texture: TextureVolume | None = None,
        tools: ToolSet | None = None,
        blood_weight: np.ndarray | None = None,
        shared: SharedMaterials | None = None,
    ) -> None:
        check_mesh(mesh, "mesh")
        self.cfg = cfg
        self.depth_only = bool(depth_only)
        if not self.depth_only and texture is None:
            raise ValueError("MeshRenderer: a texture volume is required to render RGB")
        cut = None
        if cut_faces is not None and not self.depth_only:
            cut = np.asarray(cut_faces).astype(bool).ravel()
            if len(cut) != len(mesh.faces):
                raise ValueError(
                    f"MeshRenderer: {len(cut)} cut-face labels for a mesh of {len(mesh.faces)} faces"
                )
            if not cut.any():
                cut = None
            elif cut_texture is None:
                raise ValueError("MeshRenderer: cut faces need a cut_texture")
        self.cut_faces = cut
        """(F,) bool cut-face labels in use, or None."""
        blood = None
        if blood_weight is not None and not self.depth_only:
            blood = np.asarray(blood_weight, dtype=np.float32).ravel()
            if len(blood) != len(mesh.faces) or not np.all((blood >= 0) & (blood <= 1)):
                raise ValueError(
                    f"MeshRenderer: blood_weight must be {len(mesh.faces)} values in [0, 1], "
                    f"got {len(blood)}"
                )
            if not blood.any():
                blood = None
        self.blood_weight = blood
        """(F,) float32 blood-film coverage in use, or None."""
        self.tools = tools
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

        shared = SharedMaterials() if shared is None else shared
        blood_cfg = cfg.blood if blood is not None else None
        props = shared.tissue_properties(
            mi, cfg.appearance, texture, cut, cut_texture, self.depth_only, blood_cfg
        )
        self.mesh = self._mi_mesh("tissue", mesh, props, with_normals=not self.depth_only)
        if cut is not None:
            self.mesh.add_attribute("face_cut", 1, self._buffer(cut.astype(np.float32)))
        if blood is not None:
            self.mesh.add_attribute("face_blood", 1, self._buffer(blood))
        self._tool_meshes: list = []
        if tools is not None:
            self._add_tools(tools, mesh)

        spp = int(cfg.imaging.spp)
        scene = self._scene_dict(spp)
        with deterministic_build():
            self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)
        # Ground-truth tissue depth ignores instruments: with tools it comes from a
        # geometry-only scene of the tissue alone (the tool-free render's depth exactly).
        self._depth_scene = self.scene
        self._tool_state: tuple[int, bytes] | None = None
        if self._tool_meshes:
            tissue_only = self._mi_mesh("tissue", mesh, mi.Properties(), with_normals=False)
            with deterministic_build():
                self._depth_scene = mi.load_dict({"type": "scene", "tissue": tissue_only})
            self._tool_ptrs = [mi.ShapePtr(t) for t in self._tool_meshes]
            self.place_tool(-1, np.eye(4))
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
                shared.packed(mi, texture),
                roughness=float(cfg.appearance.roughness),
                specular=float(cfg.appearance.specular),
                tissue=self.mesh,
                cut_faces=cut,
                cut_texture=None if cut is None else shared.packed(mi, cut_texture),
                blood_weight=blood,
                blood=cfg.blood,
                tools=tuple(self._tool_meshes),
                tool_bsdf=self._tool_meshes[0].bsdf() if self._tool_meshes else None,
            )
            self._gain_used = mi.Float(self._gain.ravel()[self.field_stop.ravel()])

    def _add_tools(self, tools: ToolSet, mesh: trimesh.Trimesh) -> None:
        """The instruments' Mitsuba meshes (brushed steel), their local geometry and the
        parking place of an unused one."""
        mi = self.mi
        cfg = self.cfg
        for k, tm in enumerate(tools.meshes):
            tprops = mi.Properties()
            if not self.depth_only:
                tprops["bsdf"] = mi.load_dict(steel_dict(cfg.tools))
            self._tool_meshes.append(
                self._mi_mesh(f"tool_{k}", tm, tprops, with_normals=not self.depth_only)
            )
        self._tool_local = [
            (
                np.asarray(tm.vertices, dtype=np.float64),
                np.asarray(tm.vertex_normals, dtype=np.float64),
            )
            for tm in tools.meshes
        ]
        # Where an unused instrument waits: collapsed to a point far outside the tissue.
        self._park_mm = np.asarray(mesh.bounds[1], dtype=np.float64) + 1.0e4

    def _scene_dict(self, spp: int) -> dict:
        """The Mitsuba scene: tissue, instruments and, for colour, the direct integrator,
        the sensor and the tip's spot light."""
        cfg = self.cfg
        square = int(round(spp**0.5)) ** 2 == spp
        scene: dict = {"type": "scene", "tissue": self.mesh}
        for k, tm in enumerate(self._tool_meshes):
            scene[f"tool_{k}"] = tm
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
        return scene

    def _mi_mesh(self, name: str, mesh: trimesh.Trimesh, props: Any, with_normals: bool) -> Any:
        mi = self.mi
        m = mi.Mesh(
            name, len(mesh.vertices), len(mesh.faces), props=props, has_vertex_normals=with_normals
        )
        mp = mi.traverse(m)
        mp["vertex_positions"] = np.ascontiguousarray(
            np.asarray(mesh.vertices, dtype=np.float32).ravel()
        )
        mp["faces"] = np.ascontiguousarray(np.asarray(mesh.faces, dtype=np.uint32).ravel())
        with deterministic_build():  # normals are summed over faces, in parallel otherwise
            mp.update()
            if with_normals:
                m.recompute_vertex_normals()
        return m

    def _buffer(self, values: np.ndarray) -> Any:
        """A flat float32 buffer for a mesh parameter: drjit's Float on the JIT variants,
        a numpy array on ``scalar_rgb`` (whose ``mi.Float`` is a Python float)."""
        flat = np.ascontiguousarray(values, dtype=np.float32).ravel()
        return self.mi.Float(flat) if self.jit else flat

    def place_tool(self, kind: int, T_world_from_tool: np.ndarray) -> None:
        """Put instrument ``kind`` (index into the :class:`~sim.tools.ToolSet`; -1 = none) at
        ``T_world_from_tool`` ((4, 4) float64, mm) for the next renders; the others wait
        collapsed far away. Updates the loaded scene through ``mi.traverse`` (only when the
        placement changed)."""
        if not self._tool_meshes:
            raise ValueError("MeshRenderer: built without tools")
        T = np.asarray(T_world_from_tool, dtype=np.float64)
        state = (int(kind), T.tobytes() if kind >= 0 else b"")
        if state == self._tool_state:
            return
        for k, (verts, normals) in enumerate(self._tool_local):
            if k == kind:
                world = verts @ T[:3, :3].T + T[:3, 3]
                n_world = normals @ T[:3, :3].T
            else:
                world = np.broadcast_to(self._park_mm, verts.shape)
                n_world = np.broadcast_to(np.array([0.0, 0.0, 1.0]), verts.shape)
            self.params[f"tool_{k}.vertex_positions"] = self._buffer(world)
            if not self.depth_only:
                self.params[f"tool_{k}.vertex_normals"] = self._buffer(n_world)
        with deterministic_build():  # moved vertices rebuild the scene's structure
            self.params.update()
        self._tool_state = state

    def _visible_z_and_tool(self, T: np.ndarray) -> tuple[Any, Any]:
        """Unevaluated drjit (z-depth of the first hit with instruments, NaN = miss; True
        where that hit is an instrument) along every raw pixel centre's exact ray."""
        dr, mi = self.drjit, self.mi
        R = [dr.opaque(mi.Float, float(x)) for x in T[:3, :3].ravel()]
        o = mi.Point3f(*(dr.opaque(mi.Float, float(x)) for x in T[:3, 3]))
        d = self._dirs_cam
        assert d is not None  # set on the JIT variants, the only callers
        d_world = mi.Vector3f(
            R[0] * d.x + R[1] * d.y + R[2] * d.z,
            R[3] * d.x + R[4] * d.y + R[5] * d.z,
            R[6] * d.x + R[7] * d.y + R[8] * d.z,
        )
        pi = self.scene.ray_intersect_preliminary(mi.Ray3f(o, d_world), coherent=True)
        z = pi.t * d.z
        valid = pi.is_valid() & (z > 0)
        tool = valid & (pi.shape == self._tool_ptrs[0])
        for ptr in self._tool_ptrs[1:]:
            tool |= valid & (pi.shape == ptr)
        return dr.select(valid, z, dr.nan), tool

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
            return np.stack([self._depth_via_sensor(t, self._depth_scene) for t in T])
        z = jit_z_depth(self.mi, self._depth_scene, self._dirs_cam, T)
        return np.array(z, dtype=np.float32).reshape(len(T), *self.camera.shape)

    def _depth_via_sensor(
        self, T_world_from_cam: np.ndarray, scene: object | None = None
    ) -> np.ndarray:
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
            self._depth_scene if scene is None else scene,
            sensor=self._depth_sensor,
            integrator=self._depth_integrator,
            spp=1,
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

    def render(
        self,
        T_world_from_cam: np.ndarray,
        index: int = 0,
        seed: int = 0,
        tool: tuple[int, np.ndarray] | None = None,
        effects: FrameEffects | None = None,
    ) -> RenderedFrame:
        """Depth, validity and (unless depth-only) RGB of one frame.

        T_world_from_cam : (4, 4) float64 true pose, mm. ``index`` and ``seed`` seed the
        Monte Carlo sampler and the sensor noise (same seed and index -> same bytes).
        tool : (kind, (4, 4) T_world_from_tool) of the instrument in this frame (kind -1 =
        none); renderers built with tools place none when it is None.
        effects : smoke, motion blur and lens smear (:mod:`sim.effects`); None or inactive
        effects give exactly the bytes of a render without them.
        """
        T = check_rigid(T_world_from_cam, "T_world_from_cam")
        if self._tool_meshes:
            kind, T_tool = tool if tool is not None else (-1, np.eye(4))
            self.place_tool(int(kind), T_tool)
        elif tool is not None and int(tool[0]) >= 0:
            raise ValueError("MeshRenderer: built without tools, cannot place one")
        if effects is not None and effects.active and not self.depth_only:
            return self._render_with_effects(T, index, seed, effects)
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
        vis, tmask = self._visible_host(T, depth)
        return RenderedFrame(
            depth_mm=depth, valid=valid, rgb=rgb, depth_visible_mm=vis, tool_mask=tmask
        )

    def _visible_host(
        self, T: np.ndarray, depth: np.ndarray
    ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Visible depth and tool mask (None without tools) outside the one-launch path."""
        if not self._tool_meshes:
            return None, None
        if self.jit:
            z, tool = self._visible_z_and_tool(T)
            self.drjit.eval(z, tool)
            shape = self.camera.shape
            return (
                np.array(z, dtype=np.float32).reshape(shape),
                np.array(tool, dtype=bool).reshape(shape),
            )
        vis = self._depth_via_sensor(T, self.scene)
        # scalar_rgb has no per-ray shape ids: the tool is where the visible surface lies
        # in front of the tissue.
        tmask = np.isfinite(vis) & ~(np.abs(vis - np.nan_to_num(depth, nan=np.inf)) <= 1e-3)
        return vis, tmask

    def _render_with_effects(
        self, T: np.ndarray, index: int, seed: int, fx: FrameEffects
    ) -> RenderedFrame:
        """A frame with smoke, motion blur or a lens smear: radiance on the host (the mean
        of the sub-frame renders when blurred), the effects, then the same sensor model
        (in drjit on the JIT variants)."""
        depth = self.render_depth(T)[0]
        vis, tmask = self._visible_host(T, depth)
        fs = _frame_seed(seed, index)
        if fx.blurred:
            assert fx.T_prev is not None
            poses = blur_poses(fx.T_prev, T, fx.blur.shutter, fx.blur.subframes)
            rad = np.mean(
                [self.render_radiance(p, seed=fs + j) for j, p in enumerate(poses)], axis=0
            ).astype(np.float32)
        else:
            rad = self.render_radiance(T, seed=fs)
        rad = apply_effects(rad, depth if vis is None else vis, fx)
        if self._direct is None:
            rgb = sensor_image(
                rad, self._gain, self.cfg.imaging, np.random.default_rng([int(seed), int(index), 5])
            )
        else:
            dr, mi = self.drjit, self.mi
            H, W = self.camera.shape
            used = np.ascontiguousarray(rad.reshape(-1, 3)[self._direct.used].T)
            q = self._direct.sensor(
                mi.Color3f(used), self._gain_used, self.cfg.imaging, _noise_key(seed, index)
            )
            rgbx = dr.zeros(mi.UInt32, H * W)
            dr.scatter(rgbx, q.x | (q.y << 8) | (q.z << 16), self._direct.used_index)
            dr.eval(rgbx)
            rgb = _unpack_rgb(rgbx, H, W)
        return RenderedFrame(
            depth_mm=depth, valid=np.isfinite(depth), rgb=rgb, depth_visible_mm=vis, tool_mask=tmask
        )

    def _render_jit(self, T: np.ndarray, index: int, seed: int) -> RenderedFrame:
        """RGB-D on the JIT variants: one launch for the depth rays, colour and sensor.

        The depth rays (every raw pixel centre, exact) are scheduled with the colour rays
        of the field-stop pixels and evaluated in the same launch; the sensor model runs
        in drjit on the used pixels (only the auto-exposure mean is a separate reduction),
        whose 8-bit RGB is packed into one 32-bit word and scattered into the full frame
        there too, so the host only copies the results out. With instruments, the visible
        depth and tool mask rays join the same launch.
        """
        assert self._direct is not None
        dr, mi = self.drjit, self.mi
        H, W = self.camera.shape
        z = jit_z_depth(mi, self._depth_scene, self._dirs_cam, T[None])
        dr.schedule(z)
        extra: tuple = ()
        if self._tool_meshes:
            extra = self._visible_z_and_tool(T)
            dr.schedule(*extra)
        rad = self._direct.radiance(T, seed=_frame_seed(seed, index))
        q = self._direct.sensor(rad, self._gain_used, self.cfg.imaging, _noise_key(seed, index))
        rgbx = dr.zeros(mi.UInt32, H * W)
        dr.scatter(rgbx, q.x | (q.y << 8) | (q.z << 16), self._direct.used_index)
        dr.eval(z, rgbx, *extra)
        depth = np.array(z, dtype=np.float32).reshape(H, W)
        vis = tmask = None
        if extra:
            vis = np.array(extra[0], dtype=np.float32).reshape(H, W)
            tmask = np.array(extra[1], dtype=bool).reshape(H, W)
        return RenderedFrame(
            depth_mm=depth,
            valid=np.isfinite(depth),
            rgb=_unpack_rgb(rgbx, H, W),
            depth_visible_mm=vis,
            tool_mask=tmask,
        )


def _unpack_rgb(rgbx: object, H: int, W: int) -> np.ndarray:
    """(H, W, 3) uint8 from drjit words packing r, g, b in bytes 0-2 (little-endian)."""
    rgb = np.asarray(rgbx, dtype=np.uint32).astype("<u4", copy=False).view(np.uint8)
    return np.ascontiguousarray(rgb.reshape(H, W, 4)[..., :3])
