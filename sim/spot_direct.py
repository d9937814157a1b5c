"""Direct lighting from the tip spot light, traced along the exact distorted pixel rays.

The JIT variants render colour with this one-bounce integrator instead of ``mi.render``
with Mitsuba's ``direct`` integrator. Per sample it does what ``direct`` does with one
emitter sample and no BSDF sample for a single delta light: a primary ray, the spot
light's radiance ``I * falloff(angle) / d^2``, a shadow ray, and Mitsuba's own BSDF
(the principled BSDF over the 3D texture) evaluated for that light direction; a pixel's
value is the mean of its ``spp`` samples (box filter). What it does not do, and why it
is faster (docs/sim.md, "Speed"):

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
  ray already proved the point visible from there.
"""

from __future__ import annotations

import math
from types import ModuleType

import cv2
import numpy as np

from chisel.geometry import Camera
from sim.config import LightConfig


def _undistorted_rays(camera: Camera, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 3) float64 rays (z = 1, OpenCV axes) whose distorted projection is (u, v)."""
    u = np.asarray(u, dtype=np.float64).ravel()
    v = np.asarray(v, dtype=np.float64).ravel()
    if not camera.has_distortion:
        x, y = (u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy
    else:
        pts = np.stack([u, v], axis=-1)[:, None, :]
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        und = cv2.undistortPoints(pts, camera.K, camera.dist, None, None, None, criteria)
        x, y = und[:, 0, 0], und[:, 0, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def pixel_ray_frames(camera: Camera, used: np.ndarray) -> tuple[np.ndarray, ...]:
    """Rays through the centres of the ``used`` pixels and their derivatives across a pixel.

    used : (H, W) bool, the raw pixels to trace (row-major order is kept).
    Returns (ray, d_du, d_dv), each (N, 3) float64 in the camera frame (OpenCV, z = 1 for
    ``ray``): the ray through raw pixel ``(u + a, v + b)`` for ``|a|, |b| <= 0.5`` is
    ``ray + a d_du + b d_dv`` to second order in the offset.
    """
    used = np.asarray(used, dtype=bool)
    if used.shape != camera.shape:
        raise ValueError(f"used: expected a {camera.shape} mask, got shape {used.shape}")
    u, v = camera.pixel_grid()
    u, v = u[used], v[used]
    ray = _undistorted_rays(camera, u, v)
    d_du = _undistorted_rays(camera, u + 0.5, v) - _undistorted_rays(camera, u - 0.5, v)
    d_dv = _undistorted_rays(camera, u, v + 0.5) - _undistorted_rays(camera, u, v - 0.5)
    return ray, d_du, d_dv


class SpotDirectIntegrator:
    """One-bounce direct lighting of a loaded Mitsuba scene by a spot light at the scope tip.

    mi : the Mitsuba module with a JIT variant set (``llvm_ad_rgb`` or ``cuda_ad_rgb``).
    scene : the scene to trace (the light need not be in it).
    bsdf : the BSDF of every shape in ``scene`` (the tissue has one), called directly
        instead of through the per-hit BSDF pointer.
    camera : the raw camera (distortion included).
    used : (H, W) bool, the pixels to render (the field stop); the others stay 0.
    light : the spot light (position in the camera frame, intensity, cone).
    spp : samples per pixel (4x4-style stratified when a perfect square, else uniform).
    """

    def __init__(
        self,
        mi: ModuleType,
        scene: object,
        bsdf: object,
        camera: Camera,
        used: np.ndarray,
        light: LightConfig,
        spp: int,
    ) -> None:
        import drjit as dr  # noqa: PLC0415 - only after mitsuba picked the variant

        self.mi, self.dr, self.scene, self.bsdf = mi, dr, scene, bsdf
        # Position, shading frame and wi are all the BSDF and the light need (no UVs).
        self._ray_flags = mi.RayFlags.Minimal | mi.RayFlags.ShadingFrame
        self.shape = camera.shape
        self.used = np.asarray(used, dtype=bool).ravel()
        ray, d_du, d_dv = pixel_ray_frames(camera, used)
        self.n_pixels = len(ray)

        def upload(a: np.ndarray) -> object:
            return mi.Vector3f(np.ascontiguousarray(a.T, dtype=np.float32))

        self._ray, self._d_du, self._d_dv = upload(ray), upload(d_du), upload(d_dv)
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

    def render(self, T_world_from_cam: np.ndarray, seed: int) -> np.ndarray:
        """Linear radiance of one frame.

        T_world_from_cam : (4, 4) float64 rigid pose, mm (OpenCV camera axes).
        seed : sampler seed (same seed and pose -> same values).
        Returns (H, W, 3) float32, 0 outside ``used``.
        """
        mi, dr = self.mi, self.dr
        T = np.asarray(T_world_from_cam, dtype=np.float64)
        light_pos = T[:3, :3] @ self.light_offset_mm + T[:3, 3]
        # Per-frame values travel as (non-literal) arrays so the traced kernel is the same
        # every frame and drjit reuses the compiled one.
        rot = mi.Float(np.ascontiguousarray(T[:3, :3].ravel(), dtype=np.float32))
        pos = mi.Float(np.concatenate([T[:3, 3], light_pos]).astype(np.float32))
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
        d = (
            dr.gather(mi.Vector3f, self._ray, pixel)
            + (jx - 0.5) * dr.gather(mi.Vector3f, self._d_du, pixel)
            + (jy - 0.5) * dr.gather(mi.Vector3f, self._d_dv, pixel)
        )
        d = dr.normalize(d)
        R = [dr.gather(mi.Float, rot, k) for k in range(9)]
        d_world = mi.Vector3f(
            R[0] * d.x + R[1] * d.y + R[2] * d.z,
            R[3] * d.x + R[4] * d.y + R[5] * d.z,
            R[6] * d.x + R[7] * d.y + R[8] * d.z,
        )
        origin = mi.Point3f(*(dr.gather(mi.Float, pos, k) for k in range(3)))
        ray = mi.Ray3f(origin, d_world)
        si = self.scene.ray_intersect(ray, ray_flags=self._ray_flags, coherent=True)
        active = si.is_valid()

        lp = mi.Point3f(*(dr.gather(mi.Float, pos, 3 + k) for k in range(3)))
        to_light = lp - si.p
        dist2 = dr.squared_norm(to_light)
        dist = dr.sqrt(dist2)
        wo = to_light / dist
        axis = mi.Vector3f(R[2], R[5], R[8])  # the light points along the camera's +z
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
        f = self.bsdf.eval(mi.BSDFContext(), si, si.to_local(wo), active)
        value = dr.select(active, f * (self._intensity * falloff / dist2), 0.0)
        dr.eval(value)
        per_pixel = dr.block_sum(value, spp) / spp
        out = np.zeros((self.shape[0] * self.shape[1], 3), dtype=np.float32)
        out[self.used] = np.asarray(per_pixel, dtype=np.float32).T
        return out.reshape(self.shape[0], self.shape[1], 3)
