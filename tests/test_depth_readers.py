"""Corrupt JSON where the change-aware data and the evaluation tables are read: one of the
project's errors naming the file, through the one reader (read_json_manifest), and on the
command line one line on stderr, no traceback."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from chisel.cli import main as chisel_main
from chisel.core.errors import InvalidInputError, OutsideManifestError
from chisel.depth.prior_data import phantom_step_mesh, read_step_dataset
from chisel.eval.tables import read_metrics, read_step_metrics
from chisel.io.manifest import MAX_JSON_DEPTH

CORRUPT = {
    "truncated": b'{"sequences": [{"path": "s", ',
    "not utf-8": b'{"sequences": "\xff\xfe"}',
    "too deep": b"[" * (MAX_JSON_DEPTH + 1) + b"]" * (MAX_JSON_DEPTH + 1),
    "past the recursion limit": b"[" * 100_000 + b"]" * 100_000,  # json.loads: RecursionError
    "not an object": b"[1, 2, 3]",
}


@pytest.mark.parametrize("content", CORRUPT.values(), ids=CORRUPT.keys())
def test_corrupt_step_dataset_index_names_the_file(tmp_path: Path, content: bytes) -> None:
    (tmp_path / "dataset.json").write_bytes(content)
    with pytest.raises(InvalidInputError) as info:
        read_step_dataset([tmp_path])
    assert info.value.source == str(tmp_path / "dataset.json")


@pytest.mark.parametrize("content", CORRUPT.values(), ids=CORRUPT.keys())
def test_corrupt_phantom_header_names_the_file(tmp_path: Path, content: bytes) -> None:
    (tmp_path / "phantom.json").write_bytes(content)
    with pytest.raises(InvalidInputError) as info:
        phantom_step_mesh(tmp_path, 0)
    assert info.value.source == str(tmp_path / "phantom.json")


def test_bad_entries_of_the_change_aware_manifests_name_the_file(tmp_path: Path) -> None:
    (tmp_path / "s").mkdir()
    index = tmp_path / "dataset.json"
    index.write_text(json.dumps({"sequences": [{"path": "s", "phantom_seed": "x", "step": 0}]}))
    with pytest.raises(InvalidInputError, match=r"sequences\[0\]: phantom_seed must be an integer"):
        read_step_dataset([index])
    index.write_text(json.dumps({"sequences": [{"path": "../..", "phantom_seed": 1, "step": 0}]}))
    with pytest.raises(OutsideManifestError, match="dataset.json: sequences"):
        read_step_dataset([index])
    (tmp_path / "phantom.json").write_text(json.dumps({"steps": [{"step": [], "mesh": "m.ply"}]}))
    with pytest.raises(InvalidInputError, match=r"phantom\.json: step must be an integer"):
        phantom_step_mesh(tmp_path, 0)
    (tmp_path / "phantom.json").write_text(json.dumps({"steps": [{"step": 0, "mesh": "m.ply"}]}))
    with pytest.raises(InvalidInputError, match=r"phantom\.json: .*m\.ply is not a file"):
        phantom_step_mesh(tmp_path, 0)


@pytest.mark.parametrize("content", CORRUPT.values(), ids=CORRUPT.keys())
def test_corrupt_metrics_tables_name_the_file(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "metrics.json"
    path.write_bytes(content)
    for read in (read_metrics, read_step_metrics):
        with pytest.raises(InvalidInputError) as info:
            read(path)
        assert info.value.source == str(path)


def test_cli_corrupt_files_are_one_line_naming_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = tmp_path / "data"
    data.mkdir()
    (data / "dataset.json").write_bytes(CORRUPT["truncated"])
    argv = ["depth", "train", "--kind", "change-aware", "--data", str(data)]
    assert chisel_main([*argv, "--out", str(tmp_path / "out.pt")]) == 1
    err = capsys.readouterr().err
    assert f"{data / 'dataset.json'}: invalid JSON" in err and "Traceback" not in err

    metrics = tmp_path / "metrics.json"
    metrics.write_bytes(CORRUPT["too deep"])
    argv = ["evaluate", "seeds", "--inputs", str(metrics), "--out-dir", str(tmp_path / "o")]
    assert chisel_main(argv) == 1
    err = capsys.readouterr().err
    assert f"{metrics}: JSON nested deeper" in err and "Traceback" not in err


def test_cli_eval_every_is_checked_before_the_data_and_refused_for_monocular(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out.pt"
    base = ["depth", "train", "--data", str(tmp_path / "missing"), "--out", str(out)]
    assert chisel_main([*base, "--kind", "change-aware", "--eval-every", "0"]) == 1
    assert "eval_every" in capsys.readouterr().err
    assert chisel_main([*base, "--kind", "monocular", "--eval-every", "50"]) == 1
    assert "--eval-every: is an option of --kind change-aware only" in capsys.readouterr().err
    assert not out.exists()
