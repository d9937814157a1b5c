"""Instruments in view: closed tool models in mm, tracks clear of tissue, tool mask and
depths against Open3D's ray caster, masks through the sequence folder."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import trimesh
import yaml

from chisel.core.raycast import unit_rays
from chisel.io.sequence import Sequence
from sim.appearance import texture_volume
from sim.cli import main
from sim.collision import TissueDistance
from sim.config import SimConfig, ToolsConfig, replace_in
from sim.errors import ConfigError, MeshError, PathError, PathInTissueError
from sim.paths import intraop_path
from sim.phantom import load_mesh, load_phantom
from sim.pipeline import path_target, render_phantom, sequence_seed
from sim.render import MeshRenderer
from sim.synthetic import write_toy_phantom
from sim.tools import (
    CHECK_BEHIND_LENS_MM,
    TOOL_KINDS,
    ToolTrack,
    check_tool_mesh,
    check_tool_track,
    plan_tool_track,
    tool_mesh,
    tool_set,
)

SMALL = {
    "camera.width": 64,
    "camera.height": 48,
    "imaging.spp": 1,
    "appearance.texture_voxel_mm": 1.0,
    "paths.preop_frames": 2,
    "paths.intraop_frames": 16,
    "paths.eval_poses": 1,
    "tools.enabled": True,
    "tools.fraction": 0.8,
    "tools.episode_frames": [6, 10],
}


@pytest.fixture(scope="module")
def toy(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("tools")
    phantom = load_phantom(write_toy_phantom(root / "phantom", n_bites=1))
    mesh = load_mesh(phantom.steps[1].mesh_path)
    cfg = replace_in(SimConfig(), **SMALL)
    tissue = TissueDistance(mesh)
    poses = intraop_path(
        path_target(phantom), tissue, 16, sequence_seed(cfg.seed, "intraop", 1), cfg.paths
    )
    tools = tool_set(cfg.tools, cfg.seed)
    track = plan_tool_track(tools, cfg.camera.camera(), poses, tissue, cfg.tools, seed=5)
    return root, phantom, mesh, cfg, tissue, poses, tools, track


def test_builtin_tools_are_closed_and_sized_in_mm() -> None:
    for kind, size in zip(TOOL_KINDS, (4.0, 3.0, 3.5), strict=True):
        m = tool_mesh(kind, size, 2.5, 20.0)
        assert m.is_watertight and m.volume > 0
        ext = m.extents
        assert ext[2] == pytest.approx(20.0, abs=1.0)  # length along the axis
        assert ext[0] == pytest.approx(size, rel=0.02)  # jaw width / outer diameter
    # Sizes drawn from their ranges, seeded.
    cfg = ToolsConfig()
    a, b = tool_set(cfg, 3), tool_set(cfg, 3)
    assert a.sizes_mm == b.sizes_mm
    assert cfg.forceps_jaw_width_mm[0] <= a.sizes_mm[0] <= cfg.forceps_jaw_width_mm[1]
    assert cfg.suction_diameter_mm[0] <= a.sizes_mm[1] <= cfg.suction_diameter_mm[1]


def test_bad_tool_models_are_refused_naming_the_file(tmp_path: Path) -> None:
    open_box = trimesh.creation.box(extents=[3.0, 3.0, 20.0])
    open_box.update_faces(np.arange(len(open_box.faces)) != 0)
    with pytest.raises(MeshError, match="not closed"):
        check_tool_mesh(open_box, "x")
    in_metres = trimesh.creation.box(extents=[0.003, 0.003, 0.02])
    with pytest.raises(MeshError, match="in mm"):
        check_tool_mesh(in_metres, "x")
    path = tmp_path / "tool_m.stl"
    in_metres.export(path)
    with pytest.raises(MeshError, match="tool_m.stl"):
        tool_set(ToolsConfig(model_file=str(path)), 0)
    # Through the CLI: exit 1, nothing written.
    phantom = write_toy_phantom(tmp_path / "p", n_bites=1)
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump({"tools": {"model_file": str(path)}}))
    out = tmp_path / "out"
    rc = main(
        ["render", "--phantom", str(phantom), "--out", str(out), "--tools", "--config", str(cfg)]
        + ["--width", "32", "--height", "24", "--spp", "1", "--frames", "4", "--quiet"]
    )
    assert rc == 1 and not out.exists()
    with pytest.raises(ConfigError, match="tools.fraction"):
        ToolsConfig(fraction=1.5)
    with pytest.raises(ConfigError, match="tools.kinds"):
        replace_in(SimConfig(), **{"tools.kinds": ["scalpel"]})


def test_tool_never_intersects_tissue_and_enters_from_the_edge(toy) -> None:
    _, _, mesh, cfg, tissue, poses, tools, track = toy
    assert (track.kind >= 0).sum() >= 8
    # Dense surface samples (not the planner's vertices), distances from sim.collision.
    for i in np.flatnonzero(track.kind >= 0):
        pts, _ = trimesh.sample.sample_surface(tools.meshes[track.kind[i]], 3000, seed=int(i))
        T = track.T_world_from_tool[i]
        world = pts @ T[:3, :3].T + T[:3, 3]
        Tc = np.linalg.inv(poses[i])
        cam = world @ Tc[:3, :3].T + Tc[:3, 3]
        front = cam[:, 2] >= -CHECK_BEHIND_LENS_MM
        if front.any():  # else the tool is withdrawn behind the lens
            d = tissue.signed_distance(world[front])
            assert d.min() > 0.0, (i, d.min())  # never in tissue
            # The clearance holds up to the planner's ~0.3 mm sample spacing.
            assert d.min() > cfg.tools.clearance_mm - 0.1, (i, d.min())
        # Outside the scope (radius 2 mm) everywhere.
        assert np.hypot(cam[:, 0], cam[:, 1])[cam[:, 2] <= 0].min() > 2.0
    # Same seed, same track.
    again = plan_tool_track(tools, cfg.camera.camera(), poses, tissue, cfg.tools, seed=5)
    assert np.array_equal(again.T_world_from_tool, track.T_world_from_tool)
    # A track pushed into tissue is refused.
    moved = track.T_world_from_tool.copy()
    moved[:, :3, 3] += 40.0 * poses[:, :3, 2]  # 40 mm further along the view: into the wall
    with pytest.raises(PathInTissueError, match="inside tissue"):
        check_tool_track(tools, ToolTrack(track.kind, moved), poses, tissue, 0.3)
    # Nothing can fit: a clear error naming the key.
    tight = replace_in(cfg, **{"tools.clearance_mm": 5.0, "tools.max_tries": 3})
    with pytest.raises(PathError, match="tools.max_tries"):
        plan_tool_track(tools, cfg.camera.camera(), poses, tissue, tight.tools, seed=5)


def _o3d_first_hits(meshes: list[trimesh.Trimesh], T: np.ndarray, dirs_cam: np.ndarray):
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(
            o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
            o3d.core.Tensor(np.asarray(m.faces, np.uint32)),
        )
    d = dirs_cam.reshape(-1, 3) @ T[:3, :3].T
    rays = np.concatenate([np.broadcast_to(T[:3, 3], d.shape), d], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    return hit["t_hit"].numpy(), hit["geometry_ids"].numpy()


def test_tool_mask_and_depths_against_open3d(toy) -> None:
    _, _, mesh, cfg, _, poses, tools, track = toy
    tex = texture_volume(np.stack([mesh.bounds[0] - 1, mesh.bounds[1] + 1]), cfg.appearance, 0)
    with_tools = MeshRenderer(mesh, cfg, tex, tools=tools)
    plain = MeshRenderer(mesh, cfg, tex)
    cam = with_tools.camera
    dirs = unit_rays(cam.rays_cam())
    seen = 0
    for i in np.flatnonzero(track.kind >= 0)[::2]:
        k, T_tool = int(track.kind[i]), track.T_world_from_tool[i]
        f = with_tools.render(poses[i], index=int(i), seed=1, tool=(k, T_tool))
        tool_world = tools.meshes[k].copy().apply_transform(T_tool)
        t, gid = _o3d_first_hits([mesh, tool_world], poses[i], dirs)
        ref_mask = (gid == 1).reshape(cam.shape)
        assert f.tool_mask is not None and f.depth_visible_mm is not None
        # Equal except where the ray grazes the tool's silhouette (float32 ties).
        differ = f.tool_mask != ref_mask
        assert differ.sum() <= max(2, 0.01 * ref_mask.sum()), (i, differ.sum())
        seen += int(ref_mask.sum())
        z_ref = (t * dirs.reshape(-1, 3)[:, 2]).reshape(cam.shape)
        both = np.isfinite(z_ref) & np.isfinite(f.depth_visible_mm) & ~differ
        assert np.median(np.abs(f.depth_visible_mm[both] - z_ref[both])) < 1e-3
        # Tissue behind: the tool-free render's depth exactly, and Open3D on tissue alone.
        free = plain.render(poses[i], index=int(i), seed=1)
        assert np.array_equal(f.depth_mm, free.depth_mm, equal_nan=True)
        t0, _ = _o3d_first_hits([mesh], poses[i], dirs)
        z0 = (t0 * dirs.reshape(-1, 3)[:, 2]).reshape(cam.shape)
        ok = np.isfinite(z0) & np.isfinite(f.depth_mm)
        assert np.percentile(np.abs(f.depth_mm[ok] - z0[ok]), 99) < 0.01
        # The tool is visible in the colour image where it covers the tissue.
        assert not np.array_equal(f.rgb, free.rgb) or not ref_mask.any()
    assert seen > 20  # the tool was in view


def test_render_folder_with_tools_masks_them_out(toy) -> None:
    root, phantom, _, cfg, _, _, _, _ = toy
    out = root / "render"
    render_phantom(phantom.path, out, cfg, progress=False)
    seq = Sequence(out / "step_01")
    tools_json = json.loads((out / "step_01/tools.json").read_text())
    stop = cv2.imread(str(out / "step_01/camera_mask.png"), cv2.IMREAD_GRAYSCALE)
    inner = cv2.erode(
        stop, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0
    )
    rim = (stop > 0) & (inner == 0)
    n_tool = 0
    for i in range(len(seq)):
        mask = cv2.imread(str(out / f"step_01/tool_mask/{i:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
        if (mask & (stop > 0)).any():  # the instrument enters from the edge of the view
            assert (mask & rim).any(), i
        assert not (seq.mask(i) & mask).any()  # chisel update never uses a tool pixel
        vis = np.load(out / "step_01/depth_visible" / f"{i:06d}.npy")
        depth = np.load(out / "step_01/depth" / f"{i:06d}.npy")
        assert np.all(vis[mask] > 0) and np.all((vis[mask] < depth[mask]) | (depth[mask] == 0))
        assert np.array_equal(vis[~mask], depth[~mask])
        n_tool += int(mask.any())
        assert (tools_json["frames"][i]["tool"] is None) <= (not mask.any())
    assert n_tool >= 3
    # Preop and eval sequences stay tool-free.
    assert not (out / "preop/tool_mask").exists() and not (out / "eval/step_00/tool_mask").exists()


def test_an_episode_that_cannot_be_placed_whole_is_split_in_two(toy, monkeypatch, caplog) -> None:
    # A long episode fails when the scope moves too far within it for one rigid tool pose:
    # modelled here by a clearance check that refuses every candidate over 5 frames.
    _, _, _, cfg, tissue, poses, tools, _ = toy
    tc = replace_in(cfg, **{"tools.episode_frames": [3, 10]}).tools
    whole = plan_tool_track(tools, cfg.camera.camera(), poses, tissue, tc, seed=5)
    import sim.tools as tools_mod

    real = tools_mod.tool_clearance_mm
    placed: list[tuple[int, int]] = []

    def short_only(tools_, cand, P, tissue_):  # type: ignore[no-untyped-def]
        n = len(cand.kind)
        if n > 5:
            return np.full(n, -1.0), np.full(n, 1.0)
        d_t, d_s = real(tools_, cand, P, tissue_)
        if d_t.min() >= tc.clearance_mm and d_s.min() >= 0.0:
            start = int(np.flatnonzero(np.all(np.isclose(poses, P[0]), axis=(1, 2)))[0])
            placed.append((start, start + n))
        return d_t, d_s

    monkeypatch.setattr(tools_mod, "tool_clearance_mm", short_only)
    split = plan_tool_track(tools, cfg.camera.camera(), poses, tissue, tc, seed=5)
    covered = set(np.flatnonzero(whole.kind >= 0))
    # The planner's episode layout (its first draws): one episode at least is too long.
    layout = tools_mod._episodes(len(poses), tc, np.random.default_rng([5, tc.seed, 43]))
    assert covered == {f for a, b in layout for f in range(a, b)}
    assert any(b - a > 5 for a, b in layout)
    # The same frames carry a tool, now in pieces of at most 5 frames that tile them.
    assert set(np.flatnonzero(split.kind >= 0)) == covered
    assert all(b - a <= 5 for a, b in placed)
    assert sorted(f for a, b in placed for f in range(a, b)) == sorted(covered)
    # A piece that still cannot be placed (shorter than twice the minimum: a narrow
    # passage) is left without a tool and named in a warning; the rest keep theirs.
    # First split further, then moved to other free frames (one short episode in 16 frames).
    sparse = replace_in(cfg, **{"tools.episode_frames": [3, 10], "tools.fraction": 0.25}).tools
    monkeypatch.setattr(tools_mod, "tool_clearance_mm", real)
    alone = set(
        np.flatnonzero(
            plan_tool_track(tools, cfg.camera.camera(), poses, tissue, sparse, seed=5).kind >= 0
        )
    )
    blocked = sorted(alone)[0]

    def narrow(tools_, cand, P, tissue_):  # type: ignore[no-untyped-def]
        if np.all(np.isclose(P, poses[blocked]), axis=(1, 2)).any():
            return np.full(len(cand.kind), -1.0), np.full(len(cand.kind), 1.0)
        return real(tools_, cand, P, tissue_)

    monkeypatch.setattr(tools_mod, "tool_clearance_mm", narrow)
    with caplog.at_level(logging.WARNING, logger="sim.tools"):
        moved = plan_tool_track(tools, cfg.camera.camera(), poses, tissue, sparse, seed=5)
    got = set(np.flatnonzero(moved.kind >= 0))
    # Split, and the half with the narrow frame moved: as many tool frames, none there.
    assert len(alone) == 4 and len(got) == 4 and blocked not in got and got != alone
    assert not caplog.text
    # With no moves allowed, the piece holding the narrow frame is left out (a warning
    # names it) and the rest keep their tools.
    blocked = sorted(covered)[0]
    monkeypatch.setattr(tools_mod, "RELOCATE_TRIES", 0)
    with caplog.at_level(logging.WARNING, logger="sim.tools"):
        gap = plan_tool_track(tools, cfg.camera.camera(), poses, tissue, tc, seed=5)
    got = set(np.flatnonzero(gap.kind >= 0))
    assert blocked not in got and got < covered
    assert 1 <= len(covered - got) < tc.episode_frames[0] + 1  # one piece of one episode
    assert f"frames {blocked}-" in caplog.text
    # Fewer than half of the frames asked for get a tool: an error naming the key.
    monkeypatch.setattr(
        tools_mod, "tool_clearance_mm", lambda t, c, P, s: (-np.ones(len(c.kind)),) * 2
    )
    with pytest.raises(PathError, match="tools.max_tries"):
        plan_tool_track(
            tools,
            cfg.camera.camera(),
            poses,
            tissue,
            replace_in(cfg, **{"tools.episode_frames": [3, 10], "tools.max_tries": 2}).tools,
            seed=5,
        )


def test_scenes_are_built_on_one_thread_and_render_the_same_bytes(toy, monkeypatch) -> None:
    """Built on several threads, a scene's ray-tracing structure differs from build to
    build and a ray through a shared edge may hit either triangle (frames 1 level apart at
    a pixel or two between runs; docs/results.md, twenty-seventh session). Every build and
    rebuild (the scene, the tissue-only scene, vertex normals, a tool moved) runs on one
    drjit thread, and the thread count is restored after each, also after an error."""
    import drjit as dr

    from chisel.core.mitsuba_variant import deterministic_build, load_mitsuba

    _, _, mesh, cfg, _, poses, tools, track = toy
    mi, _ = load_mitsuba(cfg.variant)  # the renderer's variant, set before patching
    tex = texture_volume(np.stack([mesh.bounds[0] - 1, mesh.bounds[1] + 1]), cfg.appearance, 0)
    before = dr.thread_count()
    with pytest.raises(RuntimeError), deterministic_build():
        assert dr.thread_count() == 1
        raise RuntimeError("a failed build")
    assert dr.thread_count() == before
    seen: dict[str, list[int]] = {"load_dict": [], "update": [], "normals": []}
    load_dict, update = mi.load_dict, mi.SceneParameters.update
    normals = mi.Mesh.recompute_vertex_normals

    def record(name, fn):  # noqa: ANN001, ANN202
        def wrapped(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            # Of the dicts loaded, scenes build a structure (BSDFs, sensors do not).
            if name != "load_dict" or args[0].get("type") == "scene":
                seen[name].append(dr.thread_count())
            return fn(*args, **kwargs)

        return wrapped

    monkeypatch.setattr(mi, "load_dict", record("load_dict", load_dict))
    monkeypatch.setattr(mi.Mesh, "recompute_vertex_normals", record("normals", normals))
    a = MeshRenderer(mesh, cfg, tex, tools=tools)
    assert seen["load_dict"] == [1, 1]  # the scene, the tissue-only scene
    assert seen["normals"] and set(seen["normals"]) == {1}
    monkeypatch.setattr(mi.SceneParameters, "update", record("update", update))
    i = int(np.flatnonzero(track.kind >= 0)[0])
    seen["update"].clear()
    a.place_tool(int(track.kind[i]), track.T_world_from_tool[i])
    assert seen["update"] == [1]
    assert dr.thread_count() == before
    b = MeshRenderer(mesh, cfg, tex, tools=tools)
    tool = (int(track.kind[i]), track.T_world_from_tool[i])
    fa = a.render(poses[i], index=i, seed=1, tool=tool)
    fb = b.render(poses[i], index=i, seed=1, tool=tool)
    assert fa.rgb.tobytes() == fb.rgb.tobytes()
    assert fa.tool_mask is not None and fb.tool_mask is not None
    assert fa.tool_mask.tobytes() == fb.tool_mask.tobytes()
