"""Bad simulator configuration, phantom manifests, meshes and paths: one clear error each.

Cases found by trying to break ``python -m sim render``: config values of the wrong type
or not finite that were accepted (or crashed), phantom.json content that gave tracebacks,
meshes in other units or frames that rendered empty images with exit status 0, and path
failures whose message did not say what was wrong.
"""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
import yaml

from sim.cli import main
from sim.collision import TissueDistance
from sim.config import (
    MAX_IMAGE_SIDE,
    CameraConfig,
    PathConfig,
    SimConfig,
    TrackingConfig,
    config_from_dict,
    config_to_dict,
    load_config,
    replace_in,
)
from sim.errors import ConfigError, MeshError, PathError, PathInTissueError, PhantomError
from sim.paths import PathTarget, eval_poses, intraop_path, preop_sweep
from sim.phantom import load_mesh, load_phantom
from sim.pipeline import path_target
from sim.synthetic import write_toy_phantom

REPO = Path(__file__).resolve().parents[1]

# -- configuration values -------------------------------------------------------------------

# (YAML mapping, dotted key the error must name, words of the problem)
BAD_VALUES: list[tuple[dict[str, Any], str, str]] = [
    ({"paths": {"preop_frames": 2.5}}, "paths.preop_frames", "expected an integer"),
    ({"paths": {"eval_poses": 1.5}}, "paths.eval_poses", "expected an integer"),
    ({"paths": {"preop_frames": "3"}}, "paths.preop_frames", "expected an integer"),
    ({"paths": {"intraop_frames": True}}, "paths.intraop_frames", "expected an integer"),
    ({"imaging": {"spp": 1.5}}, "imaging.spp", "expected an integer"),
    ({"tracking": {"latency_frames": 1.5}}, "tracking.latency_frames", "expected an integer"),
    ({"imaging": {"auto_exposure": "no"}}, "imaging.auto_exposure", "expected true or false"),
    ({"randomization": {"enabled": 1}}, "randomization.enabled", "expected true or false"),
    ({"depth_only": "yes"}, "depth_only", "expected true or false"),
    ({"light": {"intensity": math.inf}}, "light.intensity", "finite"),
    ({"imaging": {"exposure": math.inf}}, "imaging.exposure", "finite"),
    ({"paths": {"lookahead_mm": math.inf}}, "paths.lookahead_mm", "finite"),
    ({"paths": {"lookahead_mm": 10**400}}, "paths.lookahead_mm", "finite"),
    ({"tracking": {"jitter_mm": math.nan}}, "tracking.jitter_mm", "finite"),
    ({"camera": {"width": 64.5}}, "camera.width", "expected an integer"),
    ({"camera": {"fov_deg": "85"}}, "camera.fov_deg", "expected a number"),
    ({"camera": {"fov_deg": None}}, "camera.fov_deg", "expected a number"),
    ({"camera": {"width": MAX_IMAGE_SIDE + 1}}, "camera.width", f"at most {MAX_IMAGE_SIDE}"),
    ({"camera": {"height": 100000}}, "camera.height", f"at most {MAX_IMAGE_SIDE}"),
    ({"light": {"offset_mm": 5}}, "light.offset_mm", "list of 3 numbers"),
    ({"light": {"offset_mm": [0, 1]}}, "light.offset_mm", "list of 3 numbers"),
    ({"paths": {"view_distance_mm": 5}}, "paths.view_distance_mm", "list of 2 numbers"),
    ({"paths": {"up_hint": [0, 0, "z"]}}, "paths.up_hint[2]", "expected a number"),
    ({"camera": {"dist": [0, 0, 0, 0]}}, "camera.dist", "list of 5 numbers"),
    ({"camera": {"K": [[1, 2], [3, 4]]}}, "camera.K[0]", "list of 3 numbers"),
    ({"camera": {"K": "eye"}}, "camera.K", "expected a list"),
    ({"seed": True}, "seed", "expected an integer"),
    ({"variant": "gpu"}, "variant", "expected one of"),
    ({"paths": {"clearance_mm": 0.001}}, "paths.clearance_mm", "must be >= 0.1 mm"),
    ({"camera": 3}, "camera", "expected a mapping"),
    (
        {"camera": {"K": [[200, 0, 400], [0, 200, 128], [0, 0, 1]]}},
        "camera.K",
        "intrinsics do not match the image size",
    ),
    ({"camera": {"dist": [-0.5, 0, 0, 0, 0]}}, "camera.dist", "turns back"),
    ({"camera": {"dist": [1e6, 0, 0, 0, 0]}}, "camera.dist", "scales image radii"),
    (
        {"camera": {"principal_offset_px": [0, 200]}},
        "camera.principal_offset_px",
        "intrinsics do not match the image size",
    ),
]


def test_principal_point_bound_is_the_one_sequences_are_read_with() -> None:
    # On the image's edge (-0.5 .. W - 0.5) loads in both; it was [0, W - 1] here before.
    cfg = config_from_dict({"camera": {"K": [[200, 0, 319.5], [0, 200, -0.5], [0, 0, 1]]}})
    assert cfg.camera.camera().principal_point_in_image


@pytest.mark.parametrize(("data", "key", "problem"), BAD_VALUES)
def test_bad_config_value_names_file_and_key(
    tmp_path: Path, data: dict[str, Any], key: str, problem: str
) -> None:
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.source == f"{path}: {key}"
    assert problem in info.value.problem
    # The same check without a file (Python callers, config_from_dict).
    with pytest.raises(ConfigError, match=f"^{re.escape(key)}: "):
        config_from_dict(data)


def test_bad_config_file_content(tmp_path: Path) -> None:
    path = tmp_path / "cfg.yaml"
    path.write_text("[1, 2]\n")
    with pytest.raises(ConfigError, match="expected a mapping") as info:
        load_config(path)
    assert info.value.source == str(path)
    path.write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(ConfigError, match="not a text file") as info:
        load_config(path)
    assert info.value.source == str(path)
    path.write_text("camera: {width: [\n")
    with pytest.raises(ConfigError, match="invalid YAML") as info:
        load_config(path)
    assert "\n" not in str(info.value)
    path.write_text("bogus: 1\n1: 2\n")
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['1', 'bogus'\]") as info:
        load_config(path)
    assert info.value.source == str(path)


def test_cli_overrides_are_checked(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ConfigError, match="camera.width: must be at most 8192"):
        replace_in(SimConfig(), **{"camera.width": 100000})
    with pytest.raises(ConfigError, match="depth_only: expected true or false"):
        replace_in(SimConfig(), depth_only="yes")
    with pytest.raises(ConfigError, match="camera.widht: unknown configuration key"):
        replace_in(SimConfig(), **{"camera.widht": 64})
    with pytest.raises(ConfigError, match="tracking.jitter_mm: expected a finite number"):
        TrackingConfig(jitter_mm=math.inf)
    out = tmp_path / "out"
    args = ["render", "--phantom", str(tmp_path), "--out", str(out), "--quiet"]
    assert main([*args, "--width", "100000", "--height", "100000"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "camera.width: must be at most 8192 pixels" in err
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("paths: {preop_frames: 2.5}\n")
    assert main([*args, "--config", str(cfg)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{cfg}: paths.preop_frames: expected an integer" in err
    assert "Traceback" not in err and not out.exists()


def test_valid_configs_still_load_unchanged() -> None:
    assert load_config(REPO / "config" / "sim_default.yaml") == SimConfig()
    assert config_from_dict(config_to_dict(SimConfig())) == SimConfig()
    # Integers are numbers; lists become tuples; null is fine where a field is optional.
    cfg = config_from_dict(
        {
            "camera": {"fov_deg": 80, "dist": [0, 0, 0, 0, 0], "K": None},
            "light": {"intensity": 400},
            "paths": {"view_distance_mm": [5, 12]},
            "imaging": {"auto_exposure": False},
        }
    )
    assert cfg.camera.fov_deg == 80 and cfg.camera.dist == (0, 0, 0, 0, 0)
    assert cfg.paths.view_distance_mm == (5, 12) and cfg.imaging.auto_exposure is False
    assert config_to_dict(cfg)["light"]["intensity"] == 400  # recorded as written
    K = [[100.0, 0.0, 31.5], [0.0, 100.0, 23.5], [0.0, 0.0, 1.0]]
    cam = config_from_dict({"camera": {"width": 64, "height": 48, "K": K}}).camera
    assert cam.K == tuple(tuple(row) for row in K)
    assert CameraConfig(width=MAX_IMAGE_SIDE, height=8, dist=(0, 0, 0, 0, 0)).width == 8192
    # The overrides the CLI applies, with the types argparse gives.
    over = replace_in(
        SimConfig(),
        **{
            "paths.intraop_frames": 3,
            "paths.preop_frames": 3,
            "paths.eval_poses": 2,
            "camera.width": 64,
            "camera.height": 48,
            "imaging.spp": 1,
            "seed": 7,
            "tracking.jitter_mm": 0.3,
            "tracking.jitter_deg": 0.2,
            "variant": "scalar_rgb",
            "depth_only": True,
        },
    )
    assert (over.paths.preop_frames, over.camera.width, over.seed) == (3, 64, 7)
    assert over.depth_only is True and over.variant == "scalar_rgb"
    # numpy scalars are numbers too, stored as plain Python values (JSON-ready).
    tracking = TrackingConfig(jitter_mm=np.float32(0.5), latency_frames=np.int64(2))
    assert type(tracking.jitter_mm) is float and type(tracking.latency_frames) is int


# -- phantom.json and meshes ----------------------------------------------------------------


@pytest.fixture(scope="module")
def toy_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_toy_phantom(tmp_path_factory.mktemp("badcfg") / "toy", n_bites=1)


def _copy(toy_dir: Path, tmp_path: Path) -> tuple[Path, dict[str, Any]]:
    d = tmp_path / "ph"
    shutil.copytree(toy_dir, d)
    return d, json.loads((d / "phantom.json").read_text())


def _edit_step(key: str, value: Any) -> Any:
    def edit(m: dict[str, Any]) -> None:
        m["steps"][1][key] = value

    return edit


@pytest.mark.parametrize(
    ("edit", "key", "problem"),
    [
        (_edit_step("step", "one"), "steps[1].step", "expected an integer"),
        (_edit_step("step", True), "steps[1].step", "expected an integer"),
        (_edit_step("mesh", 5), "steps[1].mesh", "expected a file path"),
        (_edit_step("mesh", ""), "steps[1].mesh", "expected a file path"),
        (lambda m: m.__setitem__("seed", "abc"), "seed", "expected an integer"),
        (
            lambda m: m["target"].__setitem__("center_mm", [math.nan, 0, 0]),
            "target.center_mm",
            "not finite",
        ),
        (lambda m: m["target"].pop("normal"), "target.normal", "missing"),
        (
            lambda m: m.__setitem__("airway_path_mm", [[0, 0], [1, 1]]),
            "airway_path_mm",
            "shape (N, 3)",
        ),
    ],
)
def test_bad_phantom_json_value(
    toy_dir: Path, tmp_path: Path, edit: Any, key: str, problem: str
) -> None:
    d, manifest = _copy(toy_dir, tmp_path)
    edit(manifest)
    (d / "phantom.json").write_text(json.dumps(manifest))
    with pytest.raises(PhantomError) as info:
        load_phantom(d)
    assert info.value.source == str(d / "phantom.json")
    assert info.value.problem.startswith(f"{key}: ") and problem in info.value.problem


@pytest.mark.parametrize(
    ("content", "problem"),
    [(b"[1, 2, 3]", "expected a JSON object, got an array"), (b"\xff\xfe\x00\x81", "not a text")],
)
def test_bad_phantom_json_file(toy_dir: Path, tmp_path: Path, content: bytes, problem: str) -> None:
    d, _ = _copy(toy_dir, tmp_path)
    (d / "phantom.json").write_bytes(content)
    with pytest.raises(PhantomError, match=problem) as info:
        load_phantom(d)
    assert info.value.source == str(d / "phantom.json")


def test_text_file_named_ply_is_not_a_readable_mesh(tmp_path: Path) -> None:
    path = tmp_path / "step_00.ply"
    path.write_text("hello\nworld\n")
    with pytest.raises(MeshError, match="not a readable mesh file") as info:
        load_mesh(path)
    assert info.value.source == str(path)


@pytest.mark.parametrize(
    ("name", "change"),
    [
        ("metres", lambda m: m.apply_scale(0.001)),
        ("shifted", lambda m: m.apply_translation([200.0, 0.0, 0.0])),
    ],
)
def test_mesh_in_other_units_or_frame_is_refused_before_rendering(
    toy_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    name: str,
    change: Any,
) -> None:
    d, _ = _copy(toy_dir, tmp_path)
    for p in sorted((d / "meshes").glob("step_*.ply")):
        mesh = trimesh.load(p, force="mesh")
        change(mesh)
        mesh.export(p)
    ph = load_phantom(d)
    tissue = TissueDistance(load_mesh(ph.steps[0].mesh_path))
    with pytest.raises(PhantomError, match="other units .* or another frame") as info:
        preop_sweep(ph.airway_path_mm, ph.target_center_mm, tissue, 5, PathConfig())
    assert "target.center_mm" in info.value.problem
    assert str(ph.steps[0].mesh_path) in info.value.problem
    for paths_fn in (eval_poses, intraop_path):
        with pytest.raises(PhantomError, match="outside the bounding box"):
            paths_fn(path_target(ph), tissue, 2, 0, PathConfig())
    out = tmp_path / "out"
    args = ["render", "--phantom", str(d), "--out", str(out), "--quiet", "--depth-only"]
    assert main([*args, "--frames", "2", "--preop-frames", "2", "--eval-poses", "1"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "step_00.ply" in err and "other units" in err
    assert not out.exists()


# -- camera paths ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def toy(toy_dir: Path) -> tuple[Any, TissueDistance]:
    ph = load_phantom(toy_dir)
    return ph, TissueDistance(load_mesh(ph.steps[0].mesh_path))


def test_clearance_no_pose_can_keep(toy: tuple[Any, TissueDistance]) -> None:
    ph, tissue = toy
    # The toy's tunnel is 10 mm wide: its airway path has at most ~7.4 mm of room.
    with pytest.raises(PathError, match="no camera position along the airway keeps 50 mm") as e:
        preop_sweep(ph.airway_path_mm, ph.target_center_mm, tissue, 5, PathConfig(clearance_mm=50))
    assert e.value.source == "paths.clearance_mm"
    # Between the narrowest and the widest room: pushing the path fails, and says so.
    with pytest.raises(PathError, match="pushing it to paths.clearance_mm = 6 mm failed"):
        preop_sweep(ph.airway_path_mm, ph.target_center_mm, tissue, 5, PathConfig(clearance_mm=6))


def test_path_starting_inside_tissue_names_the_manifest(toy: tuple[Any, TissueDistance]) -> None:
    ph, tissue = toy
    airway = ph.airway_path_mm.copy()
    airway[0] = [5.0, 12.0, 0.0]  # inside the tissue block, beside the tunnel
    manifest = str(ph.path / "phantom.json")
    with pytest.raises(PathInTissueError, match="starts inside tissue") as info:
        preop_sweep(airway, ph.target_center_mm, tissue, 5, PathConfig(), source=manifest)
    assert info.value.source == manifest
    assert info.value.problem.startswith("airway_path_mm: ")
    assert tissue.source.endswith("step_00.ply") and tissue.source in info.value.problem


def test_target_inside_tissue_is_named(toy: tuple[Any, TissueDistance]) -> None:
    ph, tissue = toy
    base = path_target(ph)
    deep = PathTarget(
        base.center_mm - 3.0 * base.normal, base.normal, base.roi_box_mm, base.approach_mm
    )
    for paths_fn in (eval_poses, intraop_path):
        with pytest.raises(PathError, match=r"target.center_mm .* lies 3\.\d+ mm inside") as info:
            paths_fn(deep, tissue, 2, 0, PathConfig())
        assert info.value.source == "phantom.json"


def test_target_hidden_from_the_airway_is_named() -> None:
    # Two separate air pockets in a block: the camera's airway ends in one, the target
    # lies on the wall of the other (in the air, but no viewpoint can see it).
    block = trimesh.creation.box(extents=[60.0, 30.0, 30.0])
    pockets = [trimesh.creation.icosphere(subdivisions=3, radius=8.0) for _ in range(2)]
    pockets[0].apply_translation([-15.0, 0.0, 0.0])
    pockets[1].apply_translation([15.0, 0.0, 0.0])
    tissue = TissueDistance(block.difference(trimesh.boolean.union(pockets)))
    target = PathTarget(
        np.array([7.0, 0.0, 0.0]),  # pocket 1's wall, "facing" pocket 0 through 14 mm of tissue
        np.array([-1.0, 0.0, 0.0]),
        np.array([[5.0, -3.0, -3.0], [9.0, 3.0, 3.0]]),
        np.array([-15.0, 0.0, 0.0]),
    )
    cfg = PathConfig(max_tries=2, viewpoint_spread_mm=0.0)
    with pytest.raises(PathError, match="tissue hides target.center_mm of phantom.json"):
        eval_poses(target, tissue, 1, 0, cfg)
    with pytest.raises(PathError, match="tissue hides target.center_mm"):
        intraop_path(target, tissue, 5, 0, cfg)
