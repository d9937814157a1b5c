"""The tiled fusion kernel against a dense per-voxel reference (every voxel projected).

The kernel visits, per image tile, only the voxels of the tile's sub-frustum; a voxel
missed or updated twice on a tile border, or a tile whose depth bound is too short,
shows up here as a weight or distance that differs from the dense reference.
"""

import numpy as np
import pytest

from chisel import fusion
from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera, look_at
from chisel.fusion import integrate
from chisel.model import TsdfModel

DIST = np.array([-0.12, 0.03, 0.002, -0.001, 0.0])


def _reference(m, cam, T, depth, w=None, rgb=None, reset=None, lateral=None):
    """Dense reference of the fusion rule, in place on ``m``; returns (updated, ambiguous).

    ``ambiguous`` flags voxels on a decision boundary (a pixel border, the truncation,
    the r^2 bound) within 1e-6, where rounding may legitimately decide either way.
    """
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in m.shape], indexing="ij"), axis=-1)
    p = ijk.reshape(-1, 3) * m.voxel_size_mm + m.origin_mm
    pc = (p - T[:3, 3]) @ T[:3, :3]  # world -> camera
    uv, z = cam.project(pc)
    rays = cam.rays_cam()
    r2max = (rays[..., 0] ** 2 + rays[..., 1] ** 2).max() * 1.02 + 1e-9
    with np.errstate(invalid="ignore", divide="ignore"):
        r2 = (pc[:, 0] ** 2 + pc[:, 1] ** 2) / z**2
    uvr = uv + 0.5
    u, v = np.floor(uvr[:, 0]), np.floor(uvr[:, 1])
    amb = (np.abs(uvr - np.round(uvr)) < 1e-6).any(axis=1) | (np.abs(r2 - r2max) < 1e-9)
    ok = (z > 1e-3) & (r2 <= r2max) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
    idx = np.flatnonzero(ok)
    ui, vi = u[idx].astype(int), v[idx].astype(int)
    dm = depth[vi, ui].astype(np.float64)
    wv = np.ones(len(idx)) if w is None else w[vi, ui].astype(np.float64)
    good = np.isfinite(dm) & (dm > 0) & (wv > 0)
    idx, ui, vi, dm, wv = idx[good], ui[good], vi[good], dm[good], wv[good]
    sd = dm - z[idx]
    amb[idx[np.abs(sd + m.trunc_mm) < 1e-6]] = True
    keep = sd >= -m.trunc_mm
    idx, ui, vi, wv, sd = idx[keep], ui[keep], vi[keep], wv[keep], sd[keep]
    if lateral is not None:
        lat = lateral[vi, ui] * z[idx] / cam.fx
        sd = np.where(sd > 0, np.minimum(sd, lat), sd)
    d = np.minimum(1.0, sd / m.trunc_mm)
    t, W = m.tsdf.reshape(-1), m.weight.reshape(-1)
    if reset is not None:
        r = reset.reshape(-1)
        W[idx[r[idx] == 0]] = 0.0
        r[idx] = 1
    W0 = W[idx].astype(np.float64)
    W1 = W0 + wv
    t[idx] = (W0 * t[idx] + wv * d) / W1
    W[idx] = W1
    if rgb is not None:
        band = d < 1.0
        c = m.color.reshape(-1, 3)
        i_b = idx[band]
        val = (W0[band, None] * c[i_b] + wv[band, None] * rgb[vi[band], ui[band]]) / W1[band, None]
        c[i_b] = np.clip(val + 0.5, 0, 255).astype(np.uint8)
    updated = np.zeros(m.tsdf.size, bool)
    updated[idx] = True
    return updated.reshape(m.shape), amb.reshape(m.shape)


def _stepped_depth(cam: Camera, rng: np.random.Generator) -> np.ndarray:
    """Piecewise-constant depth (5 x 7 px blocks, 3-14 mm) with holes: steps everywhere."""
    blocks = rng.uniform(3.0, 14.0, (cam.height // 5 + 1, cam.width // 7 + 1))
    depth = np.repeat(np.repeat(blocks, 5, axis=0), 7, axis=1)[: cam.height, : cam.width]
    depth = depth.astype(np.float32)
    depth[rng.random(depth.shape) < 0.03] = np.nan
    depth[rng.random(depth.shape) < 0.01] = 0.0
    return depth


def _poses(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    out = []
    for _ in range(n):
        d = rng.normal(size=3)
        out.append(look_at(rng.uniform(-2, 2, 3), 10.0 * d / np.linalg.norm(d), rng.normal(size=3)))
    # Views along a grid axis and along a diagonal (column axis choice, degenerate slopes).
    out.append(look_at([0.13, -0.07, -3.0], [0.13, -0.07, 10.0], [0.0, 1.0, 0.0]))
    out.append(look_at([1.0, -1.0, 0.5], [9.0, 7.0, 8.5], [0.0, 0.0, 1.0]))
    return out


@pytest.mark.parametrize("tile_px", [8, fusion.TILE_PX])
@pytest.mark.parametrize("dist", [None, DIST], ids=["pinhole", "distorted"])
def test_tiled_kernel_matches_dense_reference(monkeypatch, tile_px, dist) -> None:
    monkeypatch.setattr(fusion, "TILE_PX", tile_px)
    rng = np.random.default_rng(tile_px)
    cam = Camera.from_fov(90, 70, 80.0, dist=np.zeros(5) if dist is None else dist)
    a = TsdfModel.empty([-9.75, -10.0, -9.5], [10.0, 9.5, 10.0], 0.5, 1.5, with_color=True)
    reset_a = np.zeros(a.shape, np.uint8)
    n_amb = n_upd = 0
    for f, T in enumerate(_poses(rng, 5)):
        depth = _stepped_depth(cam, rng)
        kw: dict = {}
        if f % 2 == 1:  # a change mask with fractional weights, reset and lateral bound
            w = (rng.random((cam.height // 6 + 1, cam.width // 6 + 1)) < 0.4).astype(np.float32)
            w = np.repeat(np.repeat(w, 6, axis=0), 6, axis=1)[: cam.height, : cam.width]
            w[rng.random(w.shape) < 0.1] *= 0.5
            kw = {
                "pixel_weight": w,
                "lateral_px": rng.uniform(0.5, 4.0, cam.shape).astype(np.float32),
            }
        rgb = rng.integers(0, 256, (*cam.shape, 3), dtype=np.uint8)
        b = a.copy()
        reset_b = reset_a.copy()
        reset = {"reset": reset_a} if f % 2 == 1 else {}
        n = integrate(a, cam, T, depth, rgb=rgb, **kw, **reset)
        upd, amb = _reference(
            b,
            cam,
            T,
            depth,
            w=kw.get("pixel_weight"),
            rgb=rgb,
            reset=reset_b if reset else None,
            lateral=kw.get("lateral_px"),
        )
        same = ~amb
        n_amb += (amb & (upd | (a.weight != b.weight))).sum()
        n_upd += upd.sum()
        # Exactly the reference's voxels are updated, each once (weight equal).
        np.testing.assert_array_equal(a.weight[same], b.weight[same])
        np.testing.assert_allclose(a.tsdf[same], b.tsdf[same], atol=1e-6)
        assert np.abs(a.color[same].astype(int) - b.color[same]).max() <= 1
        np.testing.assert_array_equal(reset_a[same], reset_b[same])
        assert abs(n - upd.sum()) <= amb.sum()
    assert n_upd > 10_000  # the frames do reach a good part of the grid
    assert n_amb < 1e-3 * n_upd


def test_tiles_cover_the_frustum_once() -> None:
    # Every pixel ray lies in exactly one tile and the tiles of a pixel's dilation
    # include its own tile; the tile grid spans the frustum's bounds.
    cam = Camera.from_fov(90, 70, 80.0, dist=DIST)
    tiles = fusion._camera_tiles(cam, 16)
    x0, y0, tw, th = tiles.grid
    rays = cam.rays_cam()
    tx = np.floor((rays[..., 0] - x0) / tw).astype(int)
    ty = np.floor((rays[..., 1] - y0) / th).astype(int)
    assert tx.min() >= 0 and ty.min() >= 0 and tx.max() < tiles.nx and ty.max() < tiles.ny
    own = (ty * tiles.nx + tx).ravel()
    for p in np.random.default_rng(0).integers(0, own.size, 200):
        t = own[p]
        assert p in tiles.pixels[tiles.offsets[t] : tiles.offsets[t + 1]]


def test_bad_weight_and_layout_inputs() -> None:
    cam = Camera.from_fov(32, 24, 60.0)
    m = TsdfModel.empty([-8, -8, 0.25], [8, 8, 20], 0.5, 1.5)
    depth = np.full(cam.shape, 10.0, np.float32)
    w = np.ones(cam.shape, np.float32)
    w[3, 4] = np.nan
    with pytest.raises(InvalidInputError, match="pixel_weight"):
        integrate(m, cam, np.eye(4), depth, pixel_weight=w)
    # The kernel updates flat views in place: a non-C-ordered array is refused, not copied.
    with pytest.raises(InvalidInputError, match="reset.*C-contiguous"):
        integrate(m, cam, np.eye(4), depth, reset=np.asfortranarray(np.zeros(m.shape, np.uint8)))
    f = TsdfModel(np.asfortranarray(m.tsdf), m.weight, m.T_world_from_voxel, 0.5, 1.5)
    with pytest.raises(InvalidInputError, match="model.tsdf.*C-contiguous"):
        integrate(f, cam, np.eye(4), depth)
    # Valid views of the same inputs: weights given as a strided view are fine.
    wide = np.ones((cam.height, 2 * cam.width), np.float32)[:, ::2]
    assert integrate(m, cam, np.eye(4), depth, pixel_weight=wide) > 0
