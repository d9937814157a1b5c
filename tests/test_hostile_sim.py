"""Hostile inputs to ``sim`` and ``phantoms repair``: one line naming the key, nothing read
outside a folder through a manifest, outputs replaced atomically.

Cases an audit reproduced: ``sim dataset --resume`` following a ``seed_S/render.json`` out
of its folder, tracking errors so large that NumPy overflows or SVD fails, an unknown
``tools.material`` failing inside Mitsuba, and ``phantoms repair`` refusing to replace its
own output file (and a traceback for a folder as the output).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
import yaml

import sim.dataset
from chisel.core.geometry import Camera, look_at
from chisel.io.sequence import Frame, write_sequence
from phantoms.cli import main as phantoms_main
from sim.cli import main as sim_main
from sim.config import SimConfig, TrackingConfig
from sim.config_effects import ToolsConfig
from sim.dataset import _finished_render, build_dataset
from sim.errors import ConfigError
from sim.synthetic import write_toy_phantom

SMALL = ["--frames", "2", "--preop-frames", "2", "--width", "32", "--height", "24"]
SMALL += ["--spp", "1", "--quiet", "--eval-poses", "1"]


def _one_line(capsys: pytest.CaptureFixture[str], *needles: str) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for needle in needles:
        assert needle in err, err
    return err


# ----------------------------------------------------------------- dataset --resume


def test_resume_reads_nothing_outside_a_seed_through_its_render_json(
    tmp_path: Path,
    tiny_sim_config: SimConfig,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    gen = f"{sys.executable} -m sim.synthetic"  # the toy phantom, generator contract
    out = tmp_path / "ds"
    first = build_dataset(out, [1], tiny_sim_config, bites=1, phantom_cmd=gen, progress=False)
    # A sequence outside the dataset that a tampered render.json names.
    secret = tmp_path / "outside/secret_seq"
    secret.mkdir(parents=True)
    (secret / "sequence.json").write_text(json.dumps({"num_frames": 777}))
    read: list[Path] = []
    real_reader = sim.dataset.read_json_manifest

    def recording_reader(path: Path, *args: Any, **kwargs: Any) -> Any:
        read.append(Path(path).resolve())
        return real_reader(path, *args, **kwargs)

    monkeypatch.setattr(sim.dataset, "read_json_manifest", recording_reader)
    header_path = out / "seed_1/render.json"
    for name in ["../../outside/secret_seq", str(secret)]:
        header = json.loads(header_path.read_text())
        header["sequences"]["preop"] = name
        header_path.write_text(json.dumps(header))
        read.clear()
        caplog.clear()
        with caplog.at_level("WARNING", logger="sim.dataset"):
            again = build_dataset(
                out, [1], tiny_sim_config, bites=1, phantom_cmd=gen, resume=True, progress=False
            )
        # The seed was rendered again (as for any damaged render.json), with a warning.
        assert again == first
        assert any(
            str(header_path) in r.getMessage() and "sequences.preop" in r.getMessage()
            for r in caplog.records
        ), [r.getMessage() for r in caplog.records]
        assert not [p for p in read if secret in p.parents], read
        listing = (out / "dataset.json").read_text()
        assert "outside" not in listing and ".." not in listing and "777" not in listing
        assert json.loads((out / "seed_1/render.json").read_text())["sequences"]["preop"] == "preop"


def test_resume_refuses_sequence_names_that_leave_the_seed_folder(
    tmp_path: Path, tiny_sim_config: SimConfig, caplog: pytest.LogCaptureFixture
) -> None:
    seed = tmp_path / "ds/seed_1"
    seed.mkdir(parents=True)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "sequence.json").write_text(json.dumps({"num_frames": 3}))
    (seed / "linked").symlink_to(outside, target_is_directory=True)
    (seed / "step_01").mkdir()
    (seed / "step_01/sequence.json").write_text(json.dumps({"num_frames": 3}))
    header_path = seed / "render.json"
    cases = [
        ({"preop": "linked", "steps": {"1": "step_01"}}, "sequences.preop"),
        ({"preop": "step_01", "steps": {"1": "../../outside"}}, "sequences.steps.1"),
        ({"preop": "step_01", "steps": {"x": "step_01"}}, "sequences.steps"),
        ({"preop": ["step_01"], "steps": {"1": "step_01"}}, "sequences.preop"),
    ]
    for sequences, key in cases:
        header = {"sequences": sequences, "config": {}, "num_steps": 1}
        header_path.write_text(json.dumps(header))
        caplog.clear()
        with caplog.at_level("WARNING", logger="sim.dataset"):
            assert _finished_render(header_path, tiny_sim_config, bites=1) is None
        (record,) = caplog.records
        assert f"{header_path}: {key}" in record.getMessage(), record.getMessage()


# ----------------------------------------------------------------- tracking bounds


def _write_sequence(path: Path) -> None:
    cam = Camera.from_fov(32, 24, 80)
    rng = np.random.default_rng(0)
    frames = []
    for i in range(3):
        T = look_at(
            np.array([i, 0.5 * i, 0.0]), np.array([i, 0.0, 30.0]), up=np.array([0.0, -1, 0])
        )
        depth = rng.uniform(5, 20, cam.shape).astype(np.float32)
        rgb = rng.integers(0, 255, (*cam.shape, 3), dtype=np.uint8)
        frames.append(Frame(i, T, rgb, depth, None, T))
    write_sequence(path, cam, frames)


@pytest.mark.parametrize(
    ("option", "value", "key"),
    [
        ("--latency-frames", "99999999999999999999", "tracking.latency_frames"),
        ("--latency-frames", "10001", "tracking.latency_frames"),
        ("--handeye-deg", "1e300", "tracking.handeye_deg"),
        ("--handeye-deg", "181", "tracking.handeye_deg"),
        ("--handeye-mm", "1e308", "tracking.handeye_mm"),
        ("--jitter-mm", "1e6", "tracking.jitter_mm"),
        ("--jitter-deg", "1e300", "tracking.jitter_deg"),
    ],
)
def test_retrack_refuses_tracking_errors_out_of_range(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str, value: str, key: str
) -> None:
    _write_sequence(tmp_path / "in")
    out = tmp_path / "out"
    argv = ["retrack", "--sequence", str(tmp_path / "in"), "--out", str(out), option, value]
    assert sim_main(argv) == 1
    _one_line(capsys, "sim retrack: error: ", f"{key}: must be in [0, ", option, "got ")
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_tracking_bounds_accept_their_limits() -> None:
    TrackingConfig(jitter_mm=100, jitter_deg=180, handeye_mm=1000, handeye_deg=180)
    TrackingConfig(latency_frames=10_000)
    with pytest.raises(ConfigError, match=r"tracking\.latency_frames: must be in \[0, 10000\]"):
        TrackingConfig(latency_frames=10_001)


def _render_argv(tmp_path: Path, config: dict) -> tuple[list[str], Path]:
    phantom = write_toy_phantom(tmp_path / "ph", n_bites=1)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(config))
    out = tmp_path / "render"
    argv = ["render", "--phantom", str(phantom), "--out", str(out), "--config", str(cfg)]
    return [*argv, *SMALL], out


def test_render_config_with_a_huge_latency_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv, out = _render_argv(tmp_path, {"tracking": {"latency_frames": 10**20}})
    assert sim_main(argv) == 1
    _one_line(capsys, "tracking.latency_frames: must be in [0, 10000]", str(10**20))
    assert not out.exists()


# ----------------------------------------------------------------- tools.material


def test_unknown_tool_material_is_refused_before_rendering(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import sim.pipeline  # noqa: PLC0415

    def no_render(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("rendering started")

    monkeypatch.setattr(sim.pipeline, "render_phantom", no_render)
    argv, out = _render_argv(tmp_path, {"tools": {"enabled": True, "material": "xyz"}})
    assert sim_main(argv) == 1
    _one_line(capsys, "cfg.yaml: tools.material: expected a Mitsuba conductor", "'xyz'")
    assert not out.exists()
    with pytest.raises(ConfigError, match=r"tools\.material: .*got 'cr' \(did you mean 'Cr'\?\)"):
        ToolsConfig(material="cr")
    for name in ("Cr", "Al", "Au", "none"):
        assert ToolsConfig(material=name).material == name


# ----------------------------------------------------------------- phantoms repair


def test_tools_need_at_least_one_try() -> None:
    # The material check was once written over this one: zero tries would place no tool.
    with pytest.raises(ConfigError, match=r"tools\.max_tries: must be >= 1, got 0"):
        ToolsConfig(max_tries=0)
    assert ToolsConfig(max_tries=1).max_tries == 1


def test_repair_replaces_an_existing_output_file_and_refuses_a_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    src = tmp_path / "box.ply"
    trimesh.creation.box(extents=(10.0, 10.0, 10.0)).export(src)
    existing = tmp_path / "existing.ply"
    existing.write_text("an earlier output")
    assert phantoms_main(["repair", str(src), str(existing)]) == 0
    fixed = trimesh.load_mesh(existing, process=False)
    assert fixed.is_watertight and fixed.volume == pytest.approx(1000.0, rel=0.03)
    capsys.readouterr()
    folder = tmp_path / "somefolder"
    folder.mkdir()
    (folder / "keep.txt").write_text("keep")
    assert phantoms_main(["repair", str(src), str(folder)]) == 1
    _one_line(capsys, "phantoms repair: error: ", str(folder), "is a folder")
    assert [p.name for p in folder.iterdir()] == ["keep.txt"]
    # no temporary file left beside the outputs
    assert sorted(p.name for p in tmp_path.iterdir()) == ["box.ply", "existing.ply", "somefolder"]
