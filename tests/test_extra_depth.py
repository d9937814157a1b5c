"""A researcher's own depth estimator as a method row: `chisel external-depth` and the
workflow's ``depth.extra`` (the end-to-end run is in tests/test_workflow.py)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from chisel.core.errors import InvalidInputError
from chisel.core.geometry import Camera
from chisel.depth.external import RELATIVE_MEDIAN, command_line, external_depth
from chisel.depth_source import SequenceDepth
from chisel.io.sequence import Frame, Sequence, write_sequence

H, W = 24, 32
NOISE_MM = 0.1

NOISY_GT = textwrap.dedent(
    """\
    # The "noisy ground truth" estimator: exact depth + seeded Gaussian noise, metric.
    import pathlib, sys
    import numpy as np
    src, out = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
    for i, path in enumerate(sorted((src / "depth").glob("*.npy"))):
        d = np.load(path).astype(np.float32)
        noise = np.random.default_rng(i).normal(0.0, float(sys.argv[3]), d.shape)
        d = np.where(d > 0, d + noise, np.nan).astype(np.float32)
        np.save(out / path.name, d)
    """
)


class _Brightness(torch.nn.Module):
    """A stand-in network: depth = 50 - 0.1 * grey level (brighter = nearer), any scale."""

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        return 50.0 - 0.1 * rgb.float().mean(dim=3)


def _sequence(tmp_path: Path) -> Sequence:
    cam = Camera.from_fov(W, H, 70.0)
    rng = np.random.default_rng(0)
    frames = []
    for i in range(3):
        T = np.eye(4)
        T[:3, 3] = [0.5 * i, 0.0, 0.0]
        depth = (20.0 + 5.0 * rng.random((H, W))).astype(np.float32)
        rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        frames.append(Frame(i, T, rgb=rgb, depth_mm=depth))
    return Sequence(write_sequence(tmp_path / "seq", cam, frames))


def _script(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "estimator.py"
    path.write_text(text)
    return path


def test_a_command_that_writes_noisy_ground_truth(tmp_path: Path) -> None:
    seq = _sequence(tmp_path)
    script = _script(tmp_path, NOISY_GT)
    cmd = f"{sys.executable} {script} {{input}} {{output}} {NOISE_MM}"
    out = external_depth(seq, tmp_path / "extra", command=cmd, metric=True)
    source = SequenceDepth(out, of=seq)
    assert source.is_metric
    for i in range(len(seq)):
        err = source(seq.frame(i)) - seq.depth_mm(i)
        assert abs(float(np.std(err)) - NOISE_MM) < 0.02 and abs(float(np.mean(err))) < 0.02
    meta = Sequence(out).meta["depth_prediction"]
    assert meta["command"] == cmd and meta["relative_depth"] is False


def test_a_relative_command_is_rescaled_and_declared_relative(tmp_path: Path) -> None:
    seq = _sequence(tmp_path)
    # Depth in metres, up to scale: written at median 10, the updater solves the scale.
    script = _script(tmp_path, NOISY_GT.replace("d + noise", "(d + noise) / 1000.0"))
    out = external_depth(
        seq, tmp_path / "extra", command=f"{sys.executable} {script} {{input}} {{output}} 0"
    )
    source = SequenceDepth(out, of=seq)
    assert not source.is_metric
    for i in range(len(seq)):
        d = source(seq.frame(i))
        assert abs(float(np.nanmedian(d)) - RELATIVE_MEDIAN) < 1e-3
        ratio = d / seq.depth_mm(i)
        np.testing.assert_allclose(ratio, np.nanmedian(ratio), rtol=1e-5)


def test_a_tiny_exported_torchscript_model(tmp_path: Path) -> None:
    seq = _sequence(tmp_path)
    model = tmp_path / "tiny.pt"
    torch.jit.script(_Brightness()).save(str(model))
    out = external_depth(seq, tmp_path / "extra", torchscript=model)
    source = SequenceDepth(out, of=seq)
    assert not source.is_metric
    for i in range(len(seq)):
        want = 50.0 - 0.1 * seq.rgb(i).astype(np.float64).mean(axis=2)
        want *= RELATIVE_MEDIAN / np.median(want)
        np.testing.assert_allclose(source(seq.frame(i)), want, rtol=1e-4)
    # The CLI gives the same folder's content.
    cli = tmp_path / "cli"
    r = subprocess.run(
        [sys.executable, "-m", "chisel", "external-depth", "--sequence", str(seq.path),
         "--out", str(cli), "--torchscript", str(model)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["frames"] == len(seq)
    np.testing.assert_array_equal(Sequence(cli).depth_mm(1), Sequence(out).depth_mm(1))


def test_bad_estimators_are_named(tmp_path: Path) -> None:
    seq = _sequence(tmp_path)
    out = tmp_path / "extra"
    with pytest.raises(InvalidInputError, match=r"exited with 3.*went wrong"):
        script = _script(tmp_path, "import sys; print('went wrong', file=sys.stderr); sys.exit(3)")
        external_depth(seq, out, command=f"{sys.executable} {script} {{input}} {{output}}")
    with pytest.raises(InvalidInputError, match="did not write this frame"):
        external_depth(seq, out, command="true {input} {output}")
    with pytest.raises(InvalidInputError, match="not found"):
        external_depth(seq, out, command="no-such-estimator {input} {output}")
    with pytest.raises(InvalidInputError, match=r"\{input\} and \{output\}"):
        command_line("my-net --in x", seq.path, out)
    with pytest.raises(InvalidInputError, match="exactly one"):
        external_depth(seq, out)
    # A map of the wrong shape, and a link to a file elsewhere, each named.
    wrong = _script(tmp_path, "import sys, numpy as np\n"
        "for i in range(3): np.save(f'{sys.argv[2]}/{i:06d}.npy', np.ones((5, 5), np.float32))\n")  # fmt: skip
    with pytest.raises(InvalidInputError, match=r"000000\.npy"):
        external_depth(
            seq, out, command=f"{sys.executable} {wrong} {{input}} {{output}}", metric=True
        )
    elsewhere = tmp_path / "elsewhere.npy"
    np.save(elsewhere, np.full((H, W), 20.0, np.float32))
    link = _script(tmp_path, "import os, sys\n"
        f"for i in range(3): os.symlink({str(elsewhere)!r}, f'{{sys.argv[2]}}/{{i:06d}}.npy')\n")  # fmt: skip
    with pytest.raises(InvalidInputError, match="link out of"):
        external_depth(
            seq, out, command=f"{sys.executable} {link} {{input}} {{output}}", metric=True
        )

    # A module that returns (B, 1, H, W) is named, with what it returned.
    class _Channel(torch.nn.Module):
        def forward(self, rgb: torch.Tensor) -> torch.Tensor:
            return rgb.float().mean(dim=3, keepdim=True).permute(0, 3, 1, 2) + 1.0

    model = tmp_path / "channel.pt"
    torch.jit.script(_Channel()).save(str(model))
    with pytest.raises(InvalidInputError, match=r"channel\.pt.*shape \(1, 24, 32\)"):
        external_depth(seq, out, torchscript=model)
    assert not out.exists()  # nothing written by any of them
