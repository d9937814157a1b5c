"""End-to-end rendering: CLI, render folder contract, ground truth, RGB model, export, dataset."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
import yaml

from chisel.core.geometry import look_at
from chisel.core.raycast import MeshRaycaster
from chisel.io.sequence import Sequence
from sim.appearance import randomize, texture_volume
from sim.cli import main
from sim.config import (
    ImagingConfig,
    SimConfig,
    config_from_dict,
    config_to_dict,
    load_config,
    replace_in,
)
from sim.dataset import build_dataset, parse_seeds, render_seed
from sim.errors import ConfigError, MeshError, PhantomError
from sim.imaging import field_stop_mask, sensor_image, vignetting_gain
from sim.nerfstudio import cv_from_gl_pose, export_nerfstudio
from sim.phantom import load_mesh
from sim.pipeline import render_phantom
from sim.render import MeshRenderer
from sim.synthetic import write_toy_phantom

REPO = Path(__file__).resolve().parents[1]
SMALL = ["--width", "64", "--height", "48", "--spp", "4", "--quiet"]


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("render")
    phantom = write_toy_phantom(root / "phantom", n_bites=2)
    out = root / "out"
    rc = main(
        [
            "render",
            "--phantom",
            str(phantom),
            "--out",
            str(out),
            "--frames",
            "6",
            "--preop-frames",
            "5",
            "--eval-poses",
            "3",
            "--seed",
            "7",
            *SMALL,
        ]
    )
    assert rc == 0
    return phantom, out


def test_render_folder_contract(rendered: tuple[Path, Path]) -> None:
    phantom, out = rendered
    header = json.loads((out / "render.json").read_text())
    assert header["format"] == "endoscopic-chisel/render" and header["version"] == 1
    assert header["phantom"] == str(phantom.absolute())
    assert header["variant"] in ("llvm_ad_rgb", "cuda_ad_rgb")
    assert header["num_steps"] == 2
    assert header["sequences"] == {
        "preop": "preop",
        "steps": {"1": "step_01", "2": "step_02"},
        "eval": {"0": "eval/step_00", "1": "eval/step_01", "2": "eval/step_02"},
    }
    assert config_from_dict(header["config"]).seed == 7
    assert header["randomized"] is False
    counts = {
        "preop": 5,
        "step_01": 6,
        "step_02": 6,
        "eval/step_00": 3,
        "eval/step_01": 3,
        "eval/step_02": 3,
    }
    for name, n in counts.items():
        seq = Sequence(out / name)
        assert len(seq) == n and seq.has_rgb and seq.has_depth and seq.has_mask
        assert seq.true_poses is not None and seq.camera_mask is not None
        assert seq.camera.shape == (48, 64)
        assert seq.meta["source"] == "sim"
    # Evaluation poses: identical for every step, exact (poses.txt == poses_true.txt).
    e0, e2 = Sequence(out / "eval/step_00"), Sequence(out / "eval/step_02")
    np.testing.assert_array_equal(e0.poses, e2.poses)
    np.testing.assert_array_equal(e0.poses, e0.true_poses)
    # Intraoperative sequences carry tracked poses that differ from the true ones.
    s1 = Sequence(out / "step_01")
    assert not np.allclose(s1.poses, s1.true_poses)
    assert np.abs(s1.poses[:, :3, 3] - s1.true_poses[:, :3, 3]).max() < 3.0


def test_rendered_depth_is_ground_truth_on_each_steps_mesh(rendered: tuple[Path, Path]) -> None:
    phantom, out = rendered
    meshes = [load_mesh(phantom / f"meshes/step_{k:02d}.ply") for k in range(3)]
    for name, k in [("preop", 0), ("step_02", 2), ("eval/step_01", 1)]:
        seq = Sequence(out / name)
        caster = MeshRaycaster.from_trimesh(meshes[k], backend="open3d")
        for i in (0, len(seq) - 1):
            ref = caster.render_depth(seq.camera, seq.true_poses[i])
            d = seq.depth_mm(i)
            both = np.isfinite(ref) & np.isfinite(d)
            assert both.mean() > 0.95
            assert np.median(np.abs(d[both] - ref[both])) < 1e-3
            mask = cv2.imread(str(out / name / "mask" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
            np.testing.assert_array_equal(mask, np.isfinite(d))
    # The bite changed the view of the eval poses between step 0 and step 2.
    e0, e2 = Sequence(out / "eval/step_00"), Sequence(out / "eval/step_02")
    assert any(np.nanmax(np.abs(e0.depth_mm(i) - e2.depth_mm(i))) > 0.5 for i in range(3))


def test_rgb_field_stop_and_bytes_are_deterministic(
    rendered: tuple[Path, Path], tmp_path: Path
) -> None:
    phantom, out = rendered
    seq = Sequence(out / "step_01")
    rgb = seq.rgb(2)
    stop = seq.camera_mask
    assert rgb[~stop].max() == 0
    assert rgb[stop].mean() > 20
    # Red-dominated mucosa.
    assert rgb[stop][:, 0].mean() > rgb[stop][:, 1].mean() > 0
    # Same seed -> same bytes (render again, only step_01's folder compared).
    out2 = tmp_path / "again"
    assert (
        main(
            [
                "render",
                "--phantom",
                str(phantom),
                "--out",
                str(out2),
                "--frames",
                "6",
                "--preop-frames",
                "5",
                "--eval-poses",
                "3",
                "--seed",
                "7",
                *SMALL,
            ]
        )
        == 0
    )
    for sub in ("rgb/000002.png", "depth/000003.npy", "poses.txt", "poses_true.txt"):
        assert (out / "step_01" / sub).read_bytes() == (out2 / "step_01" / sub).read_bytes(), sub


def test_depth_only_and_pose_noise_options(rendered: tuple[Path, Path], tmp_path: Path) -> None:
    phantom, _ = rendered
    out = tmp_path / "d"
    assert (
        main(
            [
                "render",
                "--phantom",
                str(phantom),
                "--out",
                str(out),
                "--frames",
                "10",
                "--preop-frames",
                "3",
                "--eval-poses",
                "2",
                "--depth-only",
                "--pose-noise-mm",
                "0",
                "--pose-noise-deg",
                "0",
                "--config",
                str(_yaml(tmp_path, {"tracking": {"handeye_mm": 0.0, "handeye_deg": 0.0}})),
                *SMALL,
            ]
        )
        == 0
    )
    seq = Sequence(out / "step_01")
    assert not seq.has_rgb and seq.has_depth and len(seq) == 10
    np.testing.assert_array_equal(seq.poses, seq.true_poses)  # zero noise -> exact
    assert json.loads((out / "render.json").read_text())["depth_only"] is True


def _yaml(tmp: Path, data: dict) -> Path:
    p = tmp / "cfg.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_failed_render_leaves_previous_output_intact(
    rendered: tuple[Path, Path], tmp_path: Path
) -> None:
    phantom, out = rendered
    broken = tmp_path / "broken"
    shutil.copytree(phantom, broken)
    box = trimesh.creation.box(extents=[5, 5, 5])
    box.update_faces(np.arange(len(box.faces)) > 0)
    box.export(broken / "meshes/step_02.ply")
    target = tmp_path / "out"
    shutil.copytree(out / "eval", target / "eval")
    before = sorted(p.name for p in target.rglob("*"))
    with pytest.raises(MeshError, match="not watertight"):
        render_phantom(
            broken, target, replace_in(SimConfig(), **{"camera.width": 64, "camera.height": 48})
        )
    assert sorted(p.name for p in target.rglob("*")) == before
    assert not list(tmp_path.glob(".out.tmp-*"))
    # Through the CLI: exit 1 with a message naming the file.
    (broken / "meshes/step_01.ply").unlink()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "sim",
            "render",
            "--phantom",
            str(broken),
            "--out",
            str(tmp_path / "o2"),
            *SMALL,
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert proc.returncode == 1
    assert "step_01.ply" in proc.stderr and "does not exist" in proc.stderr
    assert not (tmp_path / "o2").exists()


def test_cli_help_and_config_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for cmd in (
        ["--help"],
        ["render", "--help"],
        ["export-nerfstudio", "--help"],
        ["dataset", "--help"],
    ):
        with pytest.raises(SystemExit) as exc:
            main(cmd)
        assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "millimetres" in text and "z-depth" in text and "OpenGL" in text
    with pytest.raises(ConfigError, match="unknown key"):
        load_config(_yaml(tmp_path, {"camera": {"widht": 3}}))
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "none.yaml")
    with pytest.raises(ConfigError, match="imaging.spp"):
        ImagingConfig(spp=0)
    assert main(["render", "--phantom", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 1
    assert "phantom folder does not exist" in capsys.readouterr().err


def test_default_yaml_matches_dataclass_defaults() -> None:
    path = REPO / "config" / "sim_default.yaml"
    assert load_config(path) == SimConfig()
    assert config_from_dict(config_to_dict(SimConfig())) == SimConfig()


def test_inverse_square_light_and_vignetting() -> None:
    """A fronto-parallel wall: radiance at the image centre falls as 1 / d^2 (near-field spot)."""
    wall = trimesh.creation.box(extents=[200.0, 200.0, 10.0])
    wall.apply_translation([0.0, 0.0, 5.0])
    cfg = replace_in(
        SimConfig(),
        **{
            "camera.width": 64,
            "camera.height": 48,
            "camera.dist": (0.0,) * 5,
            "light.offset_mm": (0.0, 0.0, 0.0),
            "appearance.vessel_strength": 0.0,
            "appearance.color_variation": 0.0,
            "imaging.spp": 4,
        },
    )
    tex = texture_volume(
        np.array([[-100.0, -100.0, -1.0], [100.0, 100.0, 11.0]]), cfg.appearance, 0
    )
    r = MeshRenderer(wall, cfg, tex)
    cu, cv = int(round(r.camera.cx)), int(round(r.camera.cy))
    centre = []
    for d in (8.0, 16.0):
        rad = r.render_radiance(look_at([0, 0, -d], [0, 0, 0], [0, -1, 0]), seed=1)
        centre.append(rad[cv - 1 : cv + 2, cu - 1 : cu + 2].mean())
    assert centre[0] / centre[1] == pytest.approx(4.0, rel=0.05)
    gain = vignetting_gain(cfg.camera)
    stop = field_stop_mask(cfg.camera)
    assert (
        gain[~stop].max() == 0
        and gain.max() <= 1.0
        and gain[stop].min() >= 1 - cfg.camera.vignetting - 1e-6
    )
    # Sensor model without noise is a deterministic tone curve; with noise it is seeded.
    rng = np.random.default_rng
    flat = np.full((48, 64, 3), 0.1, np.float32)
    quiet = dataclasses.replace(cfg.imaging, shot_noise=0.0, read_noise=0.0, auto_exposure=False)
    img = sensor_image(flat, np.ones((48, 64), np.float32), quiet, rng(0))
    assert (img == round(255 * 0.1 ** (1 / 2.2))).all()
    noisy = dataclasses.replace(quiet, shot_noise=0.01)
    a, b = (sensor_image(flat, np.ones((48, 64), np.float32), noisy, rng(s)) for s in (1, 1))
    np.testing.assert_array_equal(a, b)
    assert a.std() > 1.0


def test_texture_is_seeded_with_vessels_and_randomization_in_range() -> None:
    cfg = SimConfig().appearance
    box = np.array([[0.0, 0.0, 0.0], [12.0, 10.0, 8.0]])
    a, b, c = texture_volume(box, cfg, 1), texture_volume(box, cfg, 1), texture_volume(box, cfg, 2)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    assert not np.array_equal(a.rgb, c.rgb)
    assert a.rgb.shape[:3] == (27, 34, 40) and a.rgb.dtype == np.float32
    # Vessels: a minority of clearly darker, redder voxels.
    g = a.rgb[..., 1]
    dark = g < 0.75 * np.median(g)
    assert 0.01 < dark.mean() < 0.3
    base = SimConfig()
    r = base.randomization
    for s in range(5):
        x = randomize(base, s)
        assert r.roughness[0] <= x.appearance.roughness <= r.roughness[1]
        assert r.exposure[0] <= x.imaging.exposure <= r.exposure[1]
        assert x.camera == base.camera and x.paths == base.paths
    assert randomize(base, 3) == randomize(base, 3) != randomize(base, 4)


def test_export_nerfstudio_axes_and_round_trip(rendered: tuple[Path, Path], tmp_path: Path) -> None:
    _, out = rendered
    seq = Sequence(out / "step_01")
    path = export_nerfstudio(out / "step_01", tmp_path / "ns")
    tj = json.loads(path.read_text())
    assert tj["camera_model"] == "OPENCV" and tj["w"] == 64 and tj["h"] == 48
    assert len(tj["frames"]) == len(seq)
    T_gl = np.array(tj["frames"][1]["transform_matrix"])
    T_cv = cv_from_gl_pose(T_gl)
    T_cv[:3, 3] *= 1000.0  # metres -> mm
    np.testing.assert_allclose(T_cv, seq.poses[1], atol=1e-9)
    # A world point seen by our camera at pixel (u, v) is seen by nerfstudio's convention
    # (OpenGL axes, -z forward, ray of pixel (u, v) through (u + 0.5, v + 0.5)) at the same pixel.
    depth = seq.depth_mm(1)
    v, u = 20, 30
    p_world = seq.poses[1] @ np.append(seq.camera.rays_cam()[v, u] * depth[v, u], 1.0)
    T_gl_mm = T_gl.copy()
    T_gl_mm[:3, 3] *= 1000.0
    p_gl = np.linalg.inv(T_gl_mm) @ p_world
    assert p_gl[2] < 0
    x, y = p_gl[0] / -p_gl[2], -p_gl[1] / -p_gl[2]
    k1, k2, k3, p1, p2 = (tj[k] for k in ("k1", "k2", "k3", "p1", "p2"))
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    np.testing.assert_allclose(
        [tj["fl_x"] * xd + tj["cx"] - 0.5, tj["fl_y"] * yd + tj["cy"] - 0.5], [u, v], atol=1e-6
    )
    frame = tj["frames"][1]
    d_ns = np.load(tmp_path / "ns" / frame["depth_file_path"])
    np.testing.assert_array_equal(d_ns, np.load(out / "step_01/depth/000001.npy"))
    assert cv2.imread(str(tmp_path / "ns" / frame["mask_path"]), cv2.IMREAD_GRAYSCALE).shape == (
        48,
        64,
    )
    assert (
        main(
            [
                "export-nerfstudio",
                "--sequence",
                str(out / "step_01"),
                "--out",
                str(tmp_path / "ns2"),
                "--true-poses",
                "--units",
                "mm",
            ]
        )
        == 0
    )
    tj2 = json.loads((tmp_path / "ns2/transforms.json").read_text())
    np.testing.assert_allclose(
        cv_from_gl_pose(np.array(tj2["frames"][0]["transform_matrix"])), seq.true_poses[0]
    )


def test_dataset_runs_generator_subprocess_and_lists_sequences(
    tmp_path: Path, tiny_sim_config: SimConfig
) -> None:
    assert parse_seeds("100-102,7") == [7, 100, 101, 102]
    with pytest.raises(ConfigError):
        parse_seeds("5-3")
    # A stand-in generator CLI with the phantoms contract (--seed --bites --out).
    gen = f"{sys.executable} -m sim.synthetic"
    cfg = tiny_sim_config
    ds = build_dataset(tmp_path / "ds", [3, 4], cfg, bites=1, phantom_cmd=gen, progress=False)
    listed = json.loads((tmp_path / "ds/dataset.json").read_text())
    assert listed == ds and listed["format"] == "endoscopic-chisel/dataset"
    assert [(e["path"], e["phantom_seed"]) for e in listed["sequences"]] == [
        ("seed_3/preop", 3),
        ("seed_3/step_01", 3),
        ("seed_4/preop", 4),
        ("seed_4/step_01", 4),
    ]
    a, b = Sequence(tmp_path / "ds/seed_3/step_01"), Sequence(tmp_path / "ds/seed_4/step_01")
    assert a.has_rgb and a.has_depth and not (tmp_path / "ds/seed_3/eval").exists()
    ca = json.loads((tmp_path / "ds/seed_3/render.json").read_text())["config"]
    cb = json.loads((tmp_path / "ds/seed_4/render.json").read_text())["config"]
    assert ca["appearance"]["roughness"] != cb["appearance"]["roughness"]  # randomised per seed
    # Master seed 0: each render is seeded with its phantom seed (earlier datasets stay
    # reproducible); the drawn values are recorded with randomisation off.
    assert ca["seed"] == 3 and ca["randomization"]["enabled"] is False
    assert json.loads((tmp_path / "ds/seed_3/render.json").read_text())["randomized"] is True
    assert len(b) == 2
    # Another master seed: another draw over the same phantom, reproducibly.
    assert render_seed(3, 7) == render_seed(3, 7) not in (3, render_seed(4, 7), render_seed(3, 8))
    build_dataset(
        tmp_path / "ds7",
        [3],
        replace_in(cfg, seed=7),
        bites=1,
        phantom_cmd=gen,
        progress=False,
    )
    c7 = json.loads((tmp_path / "ds7/seed_3/render.json").read_text())["config"]
    assert c7["seed"] == render_seed(3, 7)
    assert c7["appearance"]["roughness"] != ca["appearance"]["roughness"]
    assert not np.array_equal(Sequence(tmp_path / "ds7/seed_3/step_01").rgb(0), a.rgb(0))
    with pytest.raises(PhantomError, match="generator failed"):
        build_dataset(
            tmp_path / "ds2",
            [1],
            cfg,
            phantom_cmd=f"{sys.executable} -c 'raise SystemExit(3)'",
            progress=False,
        )


def test_dataset_generates_the_next_phantom_ahead_and_a_failure_keeps_earlier_seeds(
    tmp_path: Path, tiny_sim_config: SimConfig
) -> None:
    """The generator of seed k+1 runs while seed k renders; when it fails, seed k's render
    is finished and kept, and the error names the generator and its output."""
    script = tmp_path / "gen.py"
    script.write_text(
        "import subprocess, sys, time\n"
        "args = sys.argv[1:]\n"
        "seed = args[args.index('--seed') + 1]\n"
        f"open({str(tmp_path / 'started.txt')!r}, 'a').write(seed + ' ' + repr(time.time()) + '\\n')\n"
        "if seed == '6':\n"
        "    print('no bulla wall in reach')\n"
        "    raise SystemExit(4)\n"
        "raise SystemExit(subprocess.call([sys.executable, '-m', 'sim.synthetic', *args]))\n"
    )
    gen = f"{sys.executable} {script}"
    out = tmp_path / "ds"
    with pytest.raises(PhantomError, match="exit 4.*no bulla wall in reach"):
        build_dataset(out, [5, 6], tiny_sim_config, bites=1, phantom_cmd=gen, progress=False)
    started = [line.split() for line in (tmp_path / "started.txt").read_text().splitlines()]
    assert [s for s, _ in started] == ["5", "6"]
    # Seed 6's generator started before seed 5's render was written.
    assert float(started[1][1]) < (out / "seed_5/render.json").stat().st_mtime
    assert Sequence(out / "seed_5/step_01").has_rgb
    assert not (out / "seed_6").exists() and not (out / "dataset.json").exists()
    # --resume keeps seed 5 and generates nothing for it again.
    (tmp_path / "started.txt").unlink()
    gen_ok = f"{sys.executable} -m sim.synthetic"
    ds = build_dataset(
        out, [5, 6], tiny_sim_config, bites=1, phantom_cmd=gen_ok, resume=True, progress=False
    )
    assert [e["phantom_seed"] for e in ds["sequences"]] == [5, 5, 6, 6]


def test_render_draws_appearance_when_randomization_is_enabled(
    tmp_path: Path, tiny_sim_config: SimConfig
) -> None:
    """`randomization.enabled` in a render config: one draw from the master seed, recorded
    so that rendering with the recorded config gives the same bytes."""
    phantom = write_toy_phantom(tmp_path / "phantom", n_bites=1)
    base = replace_in(tiny_sim_config, **{"paths.eval_poses": 1, "seed": 5})
    on = replace_in(base, **{"randomization.enabled": True})
    header = render_phantom(phantom, tmp_path / "on", on, progress=False)
    drawn = randomize(on, 5)
    recorded = config_from_dict(header["config"])
    assert header["randomized"] is True and recorded.randomization.enabled is False
    assert recorded.appearance == drawn.appearance and recorded.light == drawn.light
    assert recorded.imaging == drawn.imaging and recorded.appearance != base.appearance
    render_phantom(phantom, tmp_path / "again", recorded, progress=False)
    render_phantom(phantom, tmp_path / "off", base, progress=False)
    first, again = Sequence(tmp_path / "on/step_01"), Sequence(tmp_path / "again/step_01")
    off = Sequence(tmp_path / "off/step_01")
    for i in range(2):
        np.testing.assert_array_equal(first.rgb(i), again.rgb(i))
    assert not np.array_equal(first.rgb(0), off.rgb(0))
    np.testing.assert_array_equal(first.depth_mm(0), off.depth_mm(0))  # same paths


def test_scalar_variant_fallback_renders_depth_and_rgb(
    rendered: tuple[Path, Path], tmp_path: Path
) -> None:
    """scalar_rgb (the warned fallback) renders too: depth from the sensor AOV, remapped."""
    phantom, _ = rendered
    out = tmp_path / "scalar"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "sim",
            "render",
            "--phantom",
            str(phantom),
            "--out",
            str(out),
            "--frames",
            "2",
            "--preop-frames",
            "2",
            "--eval-poses",
            "1",
            "--width",
            "32",
            "--height",
            "24",
            "--spp",
            "4",
            "--variant",
            "scalar_rgb",
            "--quiet",
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr
    assert json.loads((out / "render.json").read_text())["variant"] == "scalar_rgb"
    seq = Sequence(out / "step_01")
    caster = MeshRaycaster.from_trimesh(load_mesh(phantom / "meshes/step_01.ply"), backend="open3d")
    for i in range(2):
        d, ref = seq.depth_mm(i), caster.render_depth(seq.camera, seq.true_poses[i])
        both = np.isfinite(d) & np.isfinite(ref)
        assert both.mean() > 0.95
        # Nearest-neighbour remap of a distorted camera: sub-pixel offsets, not exact.
        assert np.median(np.abs(d[both] - ref[both])) < 0.15
        assert seq.rgb(i)[seq.camera_mask].mean() > 20


def test_end_to_end_with_real_phantom_generator(tmp_path: Path) -> None:
    """`sim dataset` runs `python -m phantoms generate` (a real, coarse phantom) and renders it."""
    out = tmp_path / "ds"
    rc = main(
        [
            "dataset",
            "--seeds",
            "0",
            "--bites",
            "1",
            "--out",
            str(out),
            "--frames",
            "3",
            "--preop-frames",
            "3",
            "--width",
            "48",
            "--height",
            "40",
            "--spp",
            "1",
            "--quiet",
            "--phantom-args",
            "--spacing-mm 1.0 --mucosa-mm 1.5 --mesh-edge-mm 1.0",
        ]
    )
    assert rc == 0
    ds = json.loads((out / "dataset.json").read_text())
    assert [e["path"] for e in ds["sequences"]] == ["seed_0/preop", "seed_0/step_01"]
    phantom = json.loads((out / "phantoms/seed_0/phantom.json").read_text())
    caster = MeshRaycaster.from_trimesh(
        load_mesh(out / "phantoms/seed_0" / phantom["steps"][1]["mesh"]), backend="open3d"
    )
    seq = Sequence(out / "seed_0/step_01")
    for i in range(len(seq)):
        d, ref = seq.depth_mm(i), caster.render_depth(seq.camera, seq.true_poses[i])
        both = np.isfinite(d) & np.isfinite(ref)
        assert both.mean() > 0.9
        assert np.median(np.abs(d[both] - ref[both])) < 1e-3
        # The camera looks at the target from the airway: it is in front, within 20 mm.
        p = np.linalg.inv(seq.true_poses[i]) @ np.append(phantom["target"]["center_mm"], 1.0)
        assert 0 < p[2] < 20.0


def test_dataset_runs_the_default_generator_once_without_ct_unless_asked(monkeypatch, tmp_path):
    import sim.dataset
    from sim.dataset import PhantomJob

    commands: list[list[str]] = []

    class Recorder:  # stands in for the generator's process
        def __init__(self, cmd, **_kwargs):
            commands.append(cmd)

        def poll(self) -> int:
            return 0

    monkeypatch.setattr(sim.dataset.subprocess, "Popen", Recorder)
    pattern = str(tmp_path / "seed_{seed}")
    PhantomJob([1, 2], pattern, 2).cancel()
    PhantomJob([1], pattern, 2, with_ct=True).cancel()
    PhantomJob([3], pattern, 2, phantom_cmd="my-gen --fast", with_ct=False).cancel()
    with pytest.raises(ValueError, match="one seed at a time"):
        PhantomJob([1, 2], pattern, 2, phantom_cmd="my-gen")
    default, with_ct, custom = commands
    assert default[1:4] == ["-m", "phantoms", "generate"] and "--no-ct" in default
    assert default[default.index("--seeds") + 1] == "1,2"
    assert default[default.index("--out") + 1] == pattern
    assert with_ct[1:4] == ["-m", "phantoms", "generate"] and "--no-ct" not in with_ct
    assert custom == [
        "my-gen",
        "--fast",
        "--seed",
        "3",
        "--bites",
        "2",
        "--out",
        pattern.replace("{seed}", "3"),
    ]


def test_dataset_generates_every_seed_in_one_generator_run(tmp_path, tiny_sim_config):
    from sim.errors import PhantomError

    coarse = "--mesh-edge-mm 1.0 --spacing-mm 1.0 --mucosa-mm 1.5"
    out = tmp_path / "ds"
    ds = build_dataset(out, [1, 2], tiny_sim_config, bites=1, phantom_args=coarse, progress=False)
    assert [e["phantom_seed"] for e in ds["sequences"]] == [1, 1, 2, 2]
    for seed in (1, 2):
        manifest = json.loads((out / f"phantoms/seed_{seed}/phantom.json").read_text())
        assert manifest["seed"] == seed and manifest["ct"] is None
        assert not (out / f"phantoms/seed_{seed}/ct").exists()
    # a generator that fails names the seed's folder and says why, and keeps what was there
    with pytest.raises(PhantomError, match="nose_mm") as info:
        build_dataset(
            tmp_path / "bad", [3, 4], tiny_sim_config, bites=1,
            phantom_args=f"{coarse} --param nose_mm=3", progress=False,
        )  # fmt: skip
    assert "seed_3" in str(info.value)
