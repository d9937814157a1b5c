"""Direct lighting from the tip spot light, traced along the exact distorted pixel rays.

The JIT variants render colour with this one-bounce integrator instead of ``mi.render``
with Mitsuba's ``direct`` integrator. Per sample it does what ``direct`` does with one
emitter sample and no BSDF sample for a single delta light: a primary ray, the spot
light's radiance ``I * falloff(angle) / d^2``, a shadow ray, and the principled BSDF
over the 3D colour texture evaluated for that light direction; a pixel's value is the
mean of its ``spp`` samples (box filter). What it does not do, and why it is faster
(docs/sim.md, "Speed"):

- it traces only the raw pixels inside the circular field stop, along the camera's exact
  distorted rays, instead of an undistorted grid that is wider than the image (for the
  remap) and rectangular; no remap afterwards;
- sub-pixel positions are 4x4 stratified (for a square ``spp``) and mapped to rays with
  the distortion linearised over the pixel (the ray through the pixel centre plus the
  ray's derivatives along u and v from central differences over one pixel): the error
  is second order in the 0.5 px offset, far below a pixel;
- the shadow ray starts at the light and ends just before the surface point, so the 16
  shadow rays of a pixel leave one point in almost one direction (a coherent packet);
  with the light at the optical centre the shadow test is skipped, exactly: the primary
  ray already proved the point visible from there;
- the hit is Embree's preliminary one (distance, triangle, barycentrics): the point is
  ``o + t d`` and the shading normal the interpolated vertex normal, which is all the
  light and the BSDF need, instead of Mitsuba's full surface interaction (frames,
  derivatives, UVs);
- the BSDF and the texture are written into the kernel (:func:`principled_eval`, the
  lobes the tissue uses, and :class:`PackedTexture`, one 32-bit read of a 10:10:10-bit
  texel per trilinear corner) instead of calling Mitsuba's BSDF, whose ``volume`` texture reads each corner
  channel by channel; both are tested equal to Mitsuba's to float precision;
- the sensor model (:meth:`SpotDirectIntegrator.sensor`) runs in drjit on the traced
  pixels, and ``MeshRenderer.render`` evaluates it and the depth rays in the same launch
  as the colour rays.
"""

from __future__ import annotations

import importlib
import math
from types import ModuleType
from typing import Any

import cv2
import numpy as np

from chisel.core.geometry import Camera
from sim.appearance import TEXEL_LEVELS, TextureVolume
from sim.config import BloodConfig, ImagingConfig, LightConfig


def undistorted_rays(camera: Camera, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 3) float64 rays (z = 1, OpenCV axes) whose distorted projection is (u, v)."""
    u = np.asarray(u, dtype=np.float64).ravel()
    v = np.asarray(v, dtype=np.float64).ravel()
    x: np.ndarray
    y: np.ndarray
    if not camera.has_distortion:
        x, y = (u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy
    else:
        pts = np.stack([u, v], axis=-1)[:, None, :]
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        und = cv2.undistortPoints(pts, camera.K, camera.dist, None, None, None, criteria)
        x, y = und[:, 0, 0], und[:, 0, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


_RAY_FRAMES: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
_RAY_FRAMES_MAX = 4


def pixel_ray_frames(camera: Camera, used: np.ndarray) -> tuple[np.ndarray, ...]:
    """Rays through the centres of the ``used`` pixels and their derivatives across a pixel.

    used : (H, W) bool, the raw pixels to trace (row-major order is kept).
    Returns (ray, d_du, d_dv), each (N, 3) float64 in the camera frame (OpenCV, z = 1 for
    ``ray``): the ray through raw pixel ``(u + a, v + b)`` for ``|a|, |b| <= 0.5`` is
    ``ray + a d_du + b d_dv`` to second order in the offset. Read-only arrays, kept for
    the next renderer of the same camera and mask (a dataset builds two per phantom, and
    the five undistortions cost ~0.15 s each time).
    """
    used = np.asarray(used, dtype=bool)
    if used.shape != camera.shape:
        raise ValueError(f"used: expected a {camera.shape} mask, got shape {used.shape}")
    key = (
        camera.width,
        camera.height,
        camera.K.tobytes(),
        camera.dist.tobytes(),
        np.packbits(used).tobytes(),
    )
    if (hit := _RAY_FRAMES.get(key)) is not None:
        return hit
    u, v = camera.pixel_grid()
    u, v = u[used], v[used]
    ray = undistorted_rays(camera, u, v)
    d_du = undistorted_rays(camera, u + 0.5, v) - undistorted_rays(camera, u - 0.5, v)
    d_dv = undistorted_rays(camera, u, v + 0.5) - undistorted_rays(camera, u, v - 0.5)
    for a in (ray, d_du, d_dv):
        a.flags.writeable = False
    if len(_RAY_FRAMES) >= _RAY_FRAMES_MAX:
        _RAY_FRAMES.pop(next(iter(_RAY_FRAMES)))
    _RAY_FRAMES[key] = (ray, d_du, d_dv)
    return ray, d_du, d_dv


def principled_eval(
    dr: ModuleType,
    n: Any,
    wi: Any,
    wo: Any,
    base: Any,
    roughness: float,
    eta: float,
) -> Any:
    """Mitsuba's ``principled`` BSDF ``eval`` (BSDF x cos(wo)) for the lobes the tissue uses.

    Those are the dielectric specular lobe (GGX, exact dielectric Fresnel, separable Smith
    shadowing) and the Disney diffuse lobe with retro-reflection; metallic, spec_trans,
    spec_tint, sheen, clearcoat, flatness and anisotropy are all 0 (principled.cpp then
    skips their code as well). Written in world space: the BSDF is isotropic, so only
    dot products with the shading normal matter and no tangent frame is needed.

    n, wi, wo : drjit Vector3f, unit shading normal, direction to the viewer, to the light.
    base : drjit Color3f base colour. roughness : principled ``roughness``.
    eta : relative index of refraction (``2 / (1 - sqrt(0.08 specular)) - 1``).
    Returns a drjit Color3f, 0 unless both directions are above the shading surface.
    """
    alpha = max(0.001, roughness * roughness)
    a2 = alpha * alpha
    cos_i = dr.dot(n, wi)
    cos_o = dr.dot(n, wo)
    active = (cos_i > 0) & (cos_o > 0)
    wh = dr.normalize(wi + wo)  # above the surface whenever wi and wo are
    cos_h = dr.dot(n, wh)
    c_ih = dr.dot(wi, wh)
    c_oh = dr.dot(wo, wh)
    # Dielectric Fresnel (fresnel.h) from outside: c_ih > 0 wherever the lobe is active.
    ct = dr.safe_sqrt(1.0 - (1.0 - c_ih * c_ih) / (eta * eta))
    a_s = (c_ih - eta * ct) / (c_ih + eta * ct)
    a_p = (ct - eta * c_ih) / (ct + eta * c_ih)
    F = 0.5 * (a_s * a_s + a_p * a_p)
    # GGX D (microfacet.h): 1 / (pi a^2 ((m_x^2 + m_y^2) / a^2 + m_z^2)^2), m_xy from
    # the tangential part of wh (no 1 - cos^2 cancellation near the normal).
    sin2_h = dr.squared_norm(wh - n * cos_h)
    D = 1.0 / (math.pi * a2 * dr.square(sin2_h / a2 + cos_h * cos_h))
    D = dr.select(D * cos_h > 1e-20, D, 0.0)

    def g1(cos_v: Any, c_vh: Any) -> Any:
        tan2 = a2 * dr.maximum(1.0 - cos_v * cos_v, 0.0) / (cos_v * cos_v)
        g = 2.0 / (1.0 + dr.sqrt(1.0 + tan2))
        return dr.select(c_vh * cos_v <= 0, 0.0, g)

    spec = dr.select(
        (c_ih > 0) & (c_oh > 0) & (F > 0), F * D * g1(cos_i, c_ih) * g1(cos_o, c_oh), 0.0
    ) / (4.0 * cos_i)

    def schlick_weight(c: Any) -> Any:
        m = dr.clip(1.0 - c, 0.0, 1.0)
        return dr.square(dr.square(m)) * m

    Fo, Fi = schlick_weight(cos_o), schlick_weight(cos_i)
    Rr = 2.0 * roughness * dr.square(c_oh)
    diffuse = (1.0 - 0.5 * Fi) * (1.0 - 0.5 * Fo) + Rr * (Fo + Fi + Fo * Fi * (Rr - 1.0))
    return dr.select(active, base * (cos_o * diffuse / math.pi) + spec, 0.0)


class PackedTexture:
    """The baked colour volume packed 10:10:10 bits in one 32-bit word per texel, trilinear
    like Mitsuba's grid.

    Mitsuba's ``gridvolume`` (a drjit ``Texture3f``, linear filter, clamp) reads each of
    the 8 corners channel by channel from float32 data; here a corner is one 32-bit
    gather, a quarter of the memory traffic (texture reads were ~10 % of a frame). The
    baked values are multiples of 1/1023 (:data:`sim.appearance.TEXEL_LEVELS`), so the
    packing loses nothing. Texel ``i`` is centred at ``(i + 0.5) / res`` of the box,
    indices clamp at the border.
    """

    def __init__(self, mi: ModuleType, texture: TextureVolume) -> None:
        words = texture.packed_10bit
        self.mi = mi
        self._data = mi.UInt32(words.ravel())
        nz, ny, nx = words.shape
        self.res = (nx, ny, nz)
        box = np.asarray(texture.box_mm, dtype=np.float64)
        self.origin = tuple(float(x) for x in box[0])
        self.texels_per_mm = tuple(
            float(r / s) for r, s in zip(self.res, box[1] - box[0], strict=True)
        )

    def eval(self, p: Any, active: Any = True) -> Any:
        """drjit Color3f base colour at world points ``p`` (drjit Point3f, mm); lanes
        outside ``active`` read nothing (0)."""
        mi = self.mi
        import drjit as dr  # noqa: PLC0415 - only after mitsuba picked the variant

        idx, frac = [], []
        for k, coord in enumerate((p.x, p.y, p.z)):
            u = (coord - self.origin[k]) * self.texels_per_mm[k] - 0.5
            u0 = dr.floor(u)
            frac.append(u - u0)
            i0 = mi.Int32(u0)
            hi = self.res[k] - 1
            idx.append((mi.UInt32(dr.clip(i0, 0, hi)), mi.UInt32(dr.clip(i0 + 1, 0, hi))))
        nx, ny = self.res[0], self.res[1]
        fx, fy, fz = frac
        out = mi.Color3f(0.0)
        for cz in range(2):
            wz = fz if cz else 1.0 - fz
            for cy in range(2):
                wy = fy if cy else 1.0 - fy
                row = (idx[2][cz] * ny + idx[1][cy]) * nx
                for cx in range(2):
                    w = wz * wy * (fx if cx else 1.0 - fx)
                    v = dr.gather(mi.UInt32, self._data, row + idx[0][cx], active)
                    out += w * mi.Color3f(
                        mi.Float(v & 1023), mi.Float((v >> 10) & 1023), mi.Float(v >> 20)
                    )
        return out * (1.0 / TEXEL_LEVELS)


def _packed(mi: ModuleType, texture: TextureVolume | PackedTexture) -> PackedTexture:
    """A volume packed for the kernel; one packed already (shared by the renderers of a
    phantom's steps) as it is."""
    return texture if isinstance(texture, PackedTexture) else PackedTexture(mi, texture)


class SpotDirectIntegrator:
    """One-bounce direct lighting of a loaded Mitsuba scene by a spot light at the scope tip.

    mi : the Mitsuba module with a JIT variant set (``llvm_ad_rgb`` or ``cuda_ad_rgb``).
    scene : the scene to trace (the light need not be in it).
    camera : the raw camera (distortion included).
    used : (H, W) bool, the pixels to render (the field stop); the others stay 0.
    light : the spot light (position in the camera frame, intensity, cone).
    spp : samples per pixel (4x4-style stratified when a perfect square, else uniform).
    texture : the tissue's base colour volume (the scene's principled BSDF uses the same),
        or that volume already packed (:class:`PackedTexture`; so is ``cut_texture``).
    roughness, specular : the principled BSDF's parameters (``sim.config.AppearanceConfig``).
    tissue : the tissue mesh in ``scene`` (default: the scene's only shape).
    cut_faces : optional (F,) bool per tissue face, True = a cut face, shaded with
        ``cut_texture`` as base colour instead of ``texture`` (same lobes; the scene's
        ``blendbsdf`` over the ``face_cut`` mesh attribute does the same).
    blood_weight : optional (F,) float blood-film coverage per tissue face; the BSDF value
        is blended ``(1 - w) f + w f_blood`` with ``blood``'s principled BSDF (uniform
        colour), as the scene's ``blendbsdf`` over ``face_blood`` does.
    tools : other meshes in ``scene`` (instruments), shaded with ``tool_bsdf`` (Mitsuba's
        own BSDF object, evaluated on Mitsuba's surface interaction of the hit).
    """

    def __init__(
        self,
        mi: ModuleType,
        scene: Any,
        camera: Camera,
        used: np.ndarray,
        light: LightConfig,
        spp: int,
        texture: TextureVolume | PackedTexture,
        roughness: float,
        specular: float,
        tissue: Any | None = None,
        cut_faces: np.ndarray | None = None,
        cut_texture: TextureVolume | PackedTexture | None = None,
        blood_weight: np.ndarray | None = None,
        blood: BloodConfig | None = None,
        tools: tuple[Any, ...] = (),
        tool_bsdf: Any | None = None,
    ) -> None:
        import drjit as dr  # noqa: PLC0415 - only after mitsuba picked the variant

        self.mi, self.dr, self.scene = mi, dr, scene
        shapes = scene.shapes()
        if tissue is None:
            if len(shapes) != 1:
                raise ValueError(
                    "SpotDirectIntegrator: name the tissue mesh of a multi-shape scene"
                )
            tissue = shapes[0]
        if not tissue.is_mesh() or not tissue.has_vertex_normals():
            raise ValueError("SpotDirectIntegrator: the tissue must be a mesh with vertex normals")
        if len(shapes) != 1 + len(tools):
            raise ValueError(
                "SpotDirectIntegrator: the scene holds shapes other than tissue and tools"
            )
        if tools and tool_bsdf is None:
            raise ValueError("SpotDirectIntegrator: tools need a tool_bsdf")
        self._tool_ptrs = [mi.ShapePtr(t) for t in tools]
        self._tool_bsdf = tool_bsdf
        self._cut = None
        self.cut_texture = None
        if cut_faces is not None and np.any(cut_faces):
            if cut_texture is None:
                raise ValueError("SpotDirectIntegrator: cut faces need a cut_texture")
            if len(cut_faces) != tissue.face_count():
                raise ValueError(
                    f"SpotDirectIntegrator: {len(cut_faces)} cut-face labels for "
                    f"{tissue.face_count()} faces"
                )
            self._cut = mi.UInt32(np.asarray(cut_faces, dtype=bool).astype(np.uint32))
            self.cut_texture = _packed(mi, cut_texture)
        self._blood = None
        if blood_weight is not None and np.any(blood_weight):
            if blood is None or len(blood_weight) != tissue.face_count():
                raise ValueError(
                    "SpotDirectIntegrator: blood_weight needs the blood config and one "
                    f"value per tissue face ({tissue.face_count()})"
                )
            self._blood = mi.Float(np.asarray(blood_weight, dtype=np.float32))
            self._blood_rgb = tuple(float(x) for x in blood.rgb)
            self._blood_roughness = float(blood.roughness)
            self._blood_eta = 2.0 / (1.0 - math.sqrt(0.08 * float(blood.specular))) - 1.0
        # The kernel interpolates the shading normal itself from the preliminary hit (the
        # BSDF and the light need nothing else), instead of Mitsuba's full surface
        # interaction: same normal to float precision, ~5 % less time per frame.
        mesh_params = mi.traverse(tissue)
        self._faces = mi.UInt32(mesh_params["faces"])
        self._vertex_normals = mi.Float(mesh_params["vertex_normals"])
        self.shape = camera.shape
        self.used = np.asarray(used, dtype=bool).ravel()
        # Where the traced pixels go in the row-major frame (drjit scatters use it).
        self.used_index = mi.UInt32(np.flatnonzero(self.used).astype(np.uint32))
        ray, d_du, d_dv = pixel_ray_frames(camera, used)
        self.n_pixels = len(ray)
        # Rays have z = 1, so their derivatives have z = 0: the 6 other numbers of a pixel
        # (padded to 8) are read by one packet gather per sample instead of 9 gathers.
        frames = np.zeros((self.n_pixels, 8), dtype=np.float32)
        frames[:, 0:2], frames[:, 2:4], frames[:, 4:6] = ray[:, :2], d_du[:, :2], d_dv[:, :2]
        self._frames = mi.Float(frames.ravel())
        # drjit's ArrayXf of this backend (drjit.llvm.ad or drjit.cuda.ad).
        self._ArrayXf = importlib.import_module(type(self._frames).__module__).ArrayXf
        self.spp = int(spp)
        side = int(round(math.sqrt(self.spp)))
        self._side = side if side * side == self.spp else 0
        self.light_offset_mm = np.asarray(light.offset_mm, dtype=np.float64)
        self.shadows = bool(np.any(self.light_offset_mm != 0.0))
        self._intensity = float(light.intensity)
        self._cos_cutoff = math.cos(math.radians(light.cutoff_deg))
        self._cos_beam = math.cos(math.radians(light.beam_width_deg))
        self._cutoff_rad = math.radians(light.cutoff_deg)
        # Mitsuba's spot: full intensity inside the beam width, then linear in the angle
        # down to 0 at the cutoff (spot.cpp ``falloff_curve``).
        width = math.radians(light.cutoff_deg - light.beam_width_deg)
        self._inv_transition = 1.0 / width if width > 0 else 0.0
        self.texture = _packed(mi, texture)
        self.roughness = float(roughness)
        # principled.cpp: eta from ``specular`` when no ``eta`` is given.
        self.eta = 2.0 / (1.0 - math.sqrt(0.08 * float(specular))) - 1.0

    def sample_rays(self, T_world_from_cam: np.ndarray, seed: int) -> tuple[Any, Any]:
        """The primary rays of every sample: ``spp`` per used pixel, pixel-major.

        T_world_from_cam : (4, 4) float64 rigid pose, mm (OpenCV camera axes).
        seed : sampler seed (same seed and pose -> same rays).
        Returns (origin, d_world): an unevaluated drjit Point3f (the camera centre, mm)
        and Vector3f (unit world directions, ``n_pixels * spp`` of them).
        """
        mi, dr = self.mi, self.dr
        T = np.asarray(T_world_from_cam, dtype=np.float64)
        # Per-frame values enter as opaque scalars (not literals) so the traced kernel is
        # the same every frame and drjit reuses the compiled one; a scalar is loaded
        # once per kernel, not gathered per lane.
        R = [dr.opaque(mi.Float, float(x)) for x in T[:3, :3].ravel()]
        origin = mi.Point3f(*(dr.opaque(mi.Float, float(x)) for x in T[:3, 3]))
        spp = self.spp
        idx = dr.arange(mi.UInt32, self.n_pixels * spp)
        pixel = idx // spp
        r0, r1 = mi.sample_tea_32(dr.opaque(mi.UInt32, int(seed) % 2**32), idx)
        jx = mi.Float(r0 >> 8) * (2.0**-24)
        jy = mi.Float(r1 >> 8) * (2.0**-24)
        if self._side:
            s = idx - pixel * spp
            jx = (mi.Float(s % self._side) + jx) / self._side
            jy = (mi.Float(s // self._side) + jy) / self._side
        fr = dr.gather(self._ArrayXf, self._frames, pixel, shape=(8, self.n_pixels * spp))
        a, b = jx - 0.5, jy - 0.5
        d = dr.normalize(
            mi.Vector3f(fr[0] + a * fr[2] + b * fr[4], fr[1] + a * fr[3] + b * fr[5], 1.0)
        )
        d_world = mi.Vector3f(
            R[0] * d.x + R[1] * d.y + R[2] * d.z,
            R[3] * d.x + R[4] * d.y + R[5] * d.z,
            R[6] * d.x + R[7] * d.y + R[8] * d.z,
        )
        return origin, d_world

    def primary_hit_mm(self, T_world_from_cam: np.ndarray, seed: int) -> Any:
        """Distance in mm along each of :meth:`sample_rays` to the first surface (inf on
        a miss), as an unevaluated drjit Float: the primary rays alone.

        Their cost is what :meth:`radiance` cannot go below on a host, shading and shadow
        rays aside; ``benchmarks/bench_render.py`` reports it as the host's bound.
        """
        mi = self.mi
        origin, d_world = self.sample_rays(T_world_from_cam, seed)
        pi = self.scene.ray_intersect_preliminary(mi.Ray3f(origin, d_world), coherent=True)
        return self.dr.select(pi.is_valid(), pi.t, self.dr.inf)

    def radiance(self, T_world_from_cam: np.ndarray, seed: int) -> Any:
        """Linear radiance of the ``used`` pixels, as an unevaluated drjit Color3f.

        T_world_from_cam : (4, 4) float64 rigid pose, mm (OpenCV camera axes).
        seed : sampler seed (same seed and pose -> same values).
        """
        mi, dr = self.mi, self.dr
        T = np.asarray(T_world_from_cam, dtype=np.float64)
        light_pos = T[:3, :3] @ self.light_offset_mm + T[:3, 3]
        lp = mi.Point3f(*(dr.opaque(mi.Float, float(x)) for x in light_pos))
        # The light points along the camera's +z.
        axis = mi.Vector3f(*(dr.opaque(mi.Float, float(x)) for x in T[:3, 2]))
        spp = self.spp
        origin, d_world = self.sample_rays(T, seed)
        ray = mi.Ray3f(origin, d_world)
        pi = self.scene.ray_intersect_preliminary(ray, coherent=True)
        active = pi.is_valid()
        tissue = active
        is_tool = None
        for ptr in self._tool_ptrs:
            hit = pi.shape == ptr
            is_tool = hit if is_tool is None else is_tool | hit
        if is_tool is not None:
            is_tool &= active
            tissue = active & ~is_tool
        p = origin + d_world * pi.t
        corners = dr.gather(mi.Vector3u, self._faces, pi.prim_index, tissue)
        b1, b2 = pi.prim_uv.x, pi.prim_uv.y
        normal = dr.normalize(
            dr.gather(mi.Vector3f, self._vertex_normals, corners.x, tissue) * (1.0 - b1 - b2)
            + dr.gather(mi.Vector3f, self._vertex_normals, corners.y, tissue) * b1
            + dr.gather(mi.Vector3f, self._vertex_normals, corners.z, tissue) * b2
        )

        to_light = lp - p
        dist2 = dr.squared_norm(to_light)
        dist = dr.sqrt(dist2)
        wo = to_light / dist
        cos_t = -dr.dot(wo, axis)
        falloff = dr.select(
            cos_t < self._cos_beam, (self._cutoff_rad - dr.acos(cos_t)) * self._inv_transition, 1.0
        )
        falloff = dr.select(cos_t >= self._cos_cutoff, falloff, 0.0)
        active &= falloff > 0
        if self.shadows:
            # From the light towards the point, stopping just short of it (no self-hit).
            shadow = mi.Ray3f(lp, -wo)
            shadow.maxt = dist * (1.0 - 1e-4)
            active &= ~self.scene.ray_test(shadow, coherent=True, active=active)
        if self._cut is None:
            base = self.texture.eval(p)
        else:
            cut = dr.gather(mi.UInt32, self._cut, pi.prim_index, tissue) > 0
            assert self.cut_texture is not None  # set together with self._cut
            base = dr.select(
                cut, self.cut_texture.eval(p, cut), self.texture.eval(p, tissue & ~cut)
            )
        f = principled_eval(dr, normal, -d_world, wo, base, self.roughness, self.eta)
        if self._blood is not None:
            w = dr.gather(mi.Float, self._blood, pi.prim_index, tissue)
            f_blood = principled_eval(
                dr,
                normal,
                -d_world,
                wo,
                mi.Color3f(*self._blood_rgb),
                self._blood_roughness,
                self._blood_eta,
            )
            f = f * (1.0 - w) + f_blood * w
        if is_tool is not None:
            # Instruments: Mitsuba's own BSDF (roughconductor) on its surface interaction.
            si = pi.compute_surface_interaction(ray, mi.RayFlags.All, is_tool)
            assert self._tool_bsdf is not None  # tools need a tool_bsdf (__init__)
            f_tool = self._tool_bsdf.eval(mi.BSDFContext(), si, si.to_local(wo), is_tool)
            f = dr.select(is_tool, f_tool, f)
        value = dr.select(active, f * (self._intensity * falloff / dist2), 0.0)
        # One kernel for all three channels (a per-channel block sum would trace it thrice).
        dr.eval(value)
        return dr.block_sum(value, spp) / spp

    def render(self, T_world_from_cam: np.ndarray, seed: int) -> np.ndarray:
        """Linear radiance of one frame.

        T_world_from_cam : (4, 4) float64 rigid pose, mm (OpenCV camera axes).
        seed : sampler seed (same seed and pose -> same values).
        Returns (H, W, 3) float32, 0 outside ``used``.
        """
        per_pixel = self.radiance(T_world_from_cam, seed)
        out = np.zeros((self.shape[0] * self.shape[1], 3), dtype=np.float32)
        out[self.used] = np.asarray(per_pixel, dtype=np.float32).T
        return out.reshape(self.shape[0], self.shape[1], 3)

    def sensor(self, radiance: Any, gain: Any, cfg: ImagingConfig, key: int) -> Any:
        """The sensor model of :func:`sim.imaging.sensor_image` in drjit, on the used pixels.

        radiance : drjit Color3f from :meth:`radiance`. gain : drjit Float, the vignetting
        gain of the used pixels. key : noise seed (same key -> same noise).
        Returns an unevaluated drjit Vector3u of 8-bit values (0 where the gain is 0).
        Shot and read noise are Gaussian as in the numpy model, drawn by Box-Muller from
        a counter-based hash of (key, pixel) instead of numpy's generator.
        """
        mi, dr = self.mi, self.dr
        signal = dr.maximum(radiance, 0.0) * gain
        exposure = mi.Float(float(cfg.exposure))
        if cfg.auto_exposure:
            n_inside = dr.count(gain > 0)
            mean = dr.sum(signal.x + signal.y + signal.z) / mi.Float(3 * dr.maximum(n_inside, 1))
            exposure *= dr.clip(cfg.ae_target / dr.maximum(mean, 1e-9), 0.05, 20.0)
        signal *= exposure
        if cfg.shot_noise > 0 or cfg.read_noise > 0:
            std = dr.sqrt(cfg.shot_noise * dr.minimum(signal, 1.0) + cfg.read_noise**2)
            pixel = dr.arange(mi.UInt32, self.n_pixels)
            k = dr.opaque(mi.UInt32, int(key) % 2**32)
            u = [
                mi.Float(r >> 8) * (2.0**-24)
                for j in range(2)
                for r in mi.sample_tea_32(k, 2 * pixel + j)
            ]
            n01 = mi.warp.square_to_std_normal(mi.Point2f(u[0], u[1]))
            n2 = mi.warp.square_to_std_normal(mi.Point2f(u[2], u[3]))
            signal += mi.Color3f(n01.x, n01.y, n2.x) * std
        signal = dr.power(dr.clip(signal, 0.0, 1.0), 1.0 / cfg.gamma)
        q = mi.Vector3u(dr.round(signal * 255.0))
        return dr.select(gain > 0, q, 0)
