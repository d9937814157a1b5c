"""Faults during ``chisel update``: SIGKILL mid-step and mid-save leave the models intact.

The subprocess runs the real CLI with one hook that, at a chosen point, writes a marker
file and waits; the test then kills it with SIGKILL from outside (as an out-of-memory
killer or a cluster scheduler would) and checks what is on disk.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from test_import_scene import SPHERE_CENTRE_MM, make_poses

from chisel.build import BuildConfig, build_preop_model
from chisel.core.geometry import Camera
from chisel.core.raycast import MeshRaycaster
from chisel.io.sequence import Frame, write_sequence
from chisel.model import TsdfModel

REPO = Path(__file__).resolve().parents[1]

# Runs in the subprocess: argv = marker, point, then the chisel command line.
HOOK = r"""
import os, pathlib, sys, time
marker, point, argv = pathlib.Path(sys.argv[1]), sys.argv[2], sys.argv[3:]
if point == "integrate":  # the 2nd frame's fusion of the step
    import chisel.updater as U
    real, calls = U.integrate, [0]
    def hooked(*a, **k):
        calls[0] += 1
        if calls[0] == 2:
            marker.write_text(point)
            time.sleep(300)
        return real(*a, **k)
    U.integrate = hooked
elif point.startswith("sigint:"):  # Ctrl-C right after the move of one output
    import signal
    # As in a terminal: a shell without job control starts background commands with
    # SIGINT ignored, and Python then installs no handler (the CLI rightly ignores it).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    real_replace, name = os.replace, point.split(":", 1)[1]
    def hooked_replace(src, dst):
        real_replace(src, dst)
        if str(dst).endswith(name):
            marker.write_text(point)
            signal.raise_signal(signal.SIGINT)  # to this thread, not any of the process's
    os.replace = hooked_replace
else:  # the final rename of the model file: its bytes are in the temporary file
    real_replace = os.replace
    def hooked_replace(src, dst):
        if str(dst).endswith(point):
            marker.write_text(point)
            time.sleep(300)
        return real_replace(src, dst)
    os.replace = hooked_replace
from chisel.cli import main
sys.exit(main(argv))
"""


def _wait_for(path: Path, proc: subprocess.Popen, timeout_s: float) -> None:
    t0 = time.monotonic()
    while not path.exists():
        if proc.poll() is not None:
            raise AssertionError(f"the update ended (rc {proc.returncode}) before the hook point")
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError("the hook point was never reached")
        time.sleep(0.05)


@pytest.fixture(scope="module")
def step_data(tmp_path_factory):
    """A preop model of a sphere interior and a step where a cap was carved 3 mm deeper."""
    d = tmp_path_factory.mktemp("update")
    cam = Camera.from_fov(64, 48, 90.0)
    poses = make_poses(6)
    preop = trimesh.creation.icosphere(4, radius=30.0)
    step = preop.copy()
    dirs = step.vertices / 30.0
    step.vertices += np.where(dirs[:, 2:3] > 0.8, 3.0 * dirs, 0.0)  # tissue removed at +z
    for m in (preop, step):
        m.apply_translation(SPHERE_CENTRE_MM)
    rc = MeshRaycaster.from_trimesh(step)
    write_sequence(
        d / "step",
        cam,
        [Frame(i, T, depth_mm=rc.render_depth(cam, T)) for i, T in enumerate(poses)],
    )
    model = build_preop_model(preop, cam, poses, BuildConfig(voxel_size_mm=1.0, trunc_mm=3.0))
    model.save(d / "m0.npz")
    return d


@pytest.mark.parametrize("point", ["integrate", "m1.npz"])
def test_update_killed_keeps_models_and_resumes(step_data, tmp_path, point) -> None:
    d = step_data
    m0_bytes = (d / "m0.npz").read_bytes()
    (tmp_path / "m1.npz").write_bytes(b"previous result of this step")
    argv = [
        "update",
        "--model",
        str(d / "m0.npz"),
        "--sequence",
        str(d / "step"),
        "--out",
        str(tmp_path / "m1.npz"),
        "--no-registration",
        "--no-progress",
    ]
    marker = tmp_path / "marker"
    proc = subprocess.Popen(
        [sys.executable, "-c", HOOK, str(marker), point, *argv],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        _wait_for(marker, proc, 120.0)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    # The input model is untouched; the step's earlier output is untouched (not truncated).
    assert (d / "m0.npz").read_bytes() == m0_bytes
    assert (tmp_path / "m1.npz").read_bytes() == b"previous result of this step"
    TsdfModel.load(d / "m0.npz")
    # Restart the step: it completes and replaces the earlier output.
    done = subprocess.run(
        [sys.executable, "-m", "chisel", *argv], cwd=REPO, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    m1 = TsdfModel.load(tmp_path / "m1.npz")
    assert m1.step == 1
    report = json.loads((tmp_path / "m1.json").read_text())
    assert report["frames_used"] and any(f["voxels_updated"] > 0 for f in report["frames"])
    # Leftovers of the killed run are only hidden temporary files, never the real names.
    names = {p.name for p in tmp_path.iterdir()}
    assert names - {"m1.npz", "m1.json", "marker"} == {n for n in names if n.startswith(".")}


def test_ctrl_c_while_the_outputs_move_lands_after_all_of_them(step_data, tmp_path) -> None:
    # The report moves first and the model last; Ctrl-C between them used to leave the
    # new report beside the step's earlier model.
    d = step_data
    (tmp_path / "m1.npz").write_bytes(b"previous result of this step")
    (tmp_path / "m1.json").write_text("previous report")
    argv = ["update", "--model", str(d / "m0.npz"), "--sequence", str(d / "step")]
    argv += ["--out", str(tmp_path / "m1.npz"), "--no-registration", "--no-progress"]
    marker = tmp_path / "marker"
    done = subprocess.run(
        [sys.executable, "-c", HOOK, str(marker), "sigint:m1.json", *argv],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert marker.exists(), done.stderr
    assert done.returncode == 130, done.stderr  # the interrupt is still reported
    assert TsdfModel.load(tmp_path / "m1.npz").step == 1
    report = json.loads((tmp_path / "m1.json").read_text())
    assert report["step"] == 1
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
