"""Inputs whose links (or named paths) lead out of their own folder are refused.

House rule (docs/bad-inputs.md): an input folder or manifest never makes the program read
or copy a file outside its folder. Three holes, each with its hostile input and a positive
control (the same input without the escape reads), so every test can fail:

1. a sequence folder whose file or subfolder (``rgb/000001.png``, ``depth/``,
   ``poses.txt``, ...) is a link to another folder (``sim export-nerfstudio`` copied it);
2. a step dataset whose ``phantoms/seed_S`` is a link to another dataset's phantom;
3. an NRRD header whose ``data file:`` names ``../outside/x.raw``, an absolute path or a
   link out (SimpleITK read it).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
import trimesh
from small_sequences import write_small_sequence

from chisel.cli import main as chisel_main
from chisel.core.errors import OutsideManifestError
from chisel.depth.prior_data import phantom_step_mesh, read_step_dataset
from chisel.io.ct import load_ct_surface, read_ct_volume
from chisel.io.sequence import Frame, Sequence
from sim.cli import main as sim_main
from sim.nerfstudio import export_nerfstudio

# --- 1. a sequence folder ---------------------------------------------------------------


def read_all(path: Path, allow_outside: bool = False) -> list[Frame]:
    seq = Sequence(path, allow_outside=True) if allow_outside else Sequence(path)
    return list(seq)


def replace_by_link(link: Path, target: Path) -> None:
    """Make ``link`` (a file or folder) a symbolic link to ``target``."""
    if link.is_dir() and not link.is_symlink():
        for p in link.iterdir():
            p.unlink()
        link.rmdir()
    else:
        link.unlink()
    link.symlink_to(target, target_is_directory=target.is_dir())


PARTS = [
    "rgb/000001.png",
    "depth/000001.npy",
    "mask/000001.png",
    "poses.txt",
    "poses_true.txt",
    "camera_mask.png",
    "sequence.json",
    "rgb",
    "depth",
    "mask",
]


@pytest.fixture
def two_seqs(tmp_path: Path) -> tuple[Path, Path]:
    """A patient's sequence and, beside it, another patient's (same camera, other data)."""
    return write_small_sequence(tmp_path / "patient_a" / "seq"), write_small_sequence(
        tmp_path / "patient_b" / "seq", 1
    )


@pytest.mark.parametrize("part", PARTS)
def test_sequence_part_linking_out_is_refused(two_seqs: tuple[Path, Path], part: str) -> None:
    seq, other = two_seqs
    replace_by_link(seq / part, other / part)
    with pytest.raises(OutsideManifestError, match=re.escape(f"names '{part}', which is ")) as e:
        read_all(seq)
    assert "outside the manifest's folder" in str(e.value)
    # The message names the commands' flag and the Python opt-in.
    assert "allow_outside=True to chisel.io.sequence.Sequence" in str(e.value)
    assert "--allow-outside-sequence to chisel build, update or render-depth" in str(e.value)


@pytest.mark.parametrize("part", PARTS)
def test_sequence_part_linking_out_reads_when_allowed(
    two_seqs: tuple[Path, Path], part: str
) -> None:
    seq, other = two_seqs
    replace_by_link(seq / part, other / part)
    assert len(read_all(seq, allow_outside=True)) == 3


@pytest.mark.parametrize("part", PARTS)
def test_sequence_part_linking_inside_reads(tmp_path: Path, part: str) -> None:
    """Positive control: the same link, to a copy kept inside the folder, reads; so do
    hard links (they are no links)."""
    seq = write_small_sequence(tmp_path / "seq")
    spare = write_small_sequence(seq / "spare", 1)  # a copy inside the sequence folder
    replace_by_link(seq / part, spare / part)
    frames = read_all(seq)
    assert len(frames) == 3
    hard = write_small_sequence(tmp_path / "hard")
    for name in ("rgb/000001.png", "depth/000001.npy", "poses.txt"):
        (hard / name).unlink()
        os.link(spare / name, hard / name)
    assert len(read_all(hard)) == 3


def test_export_nerfstudio_of_a_linked_frame_writes_nothing(
    two_seqs: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    seq, other = two_seqs
    replace_by_link(seq / "rgb" / "000002.png", other / "rgb" / "000002.png")
    out = tmp_path / "ns"
    with pytest.raises(OutsideManifestError, match=re.escape("'rgb/000002.png'")):
        export_nerfstudio(seq, out)
    assert not out.exists()
    rc = sim_main(["export-nerfstudio", "--sequence", str(seq), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert "'rgb/000002.png'" in err and "outside the manifest's folder" in err
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["patient_a", "patient_b"]


def test_export_nerfstudio_of_an_inside_link_copies_it(tmp_path: Path) -> None:
    """Positive control of the export: a link that stays inside is exported."""
    seq = write_small_sequence(tmp_path / "seq")
    (seq / "rgb" / "000002.png").unlink()
    (seq / "rgb" / "000002.png").symlink_to("000000.png")
    path = export_nerfstudio(seq, tmp_path / "ns")
    images = sorted(p.name for p in (path.parent / "images").iterdir())
    assert images == ["000000.png", "000001.png", "000002.png"]
    assert (path.parent / "images" / "000002.png").read_bytes() == (
        seq / "rgb" / "000000.png"
    ).read_bytes()


# --- 2. a step dataset's phantom folder -------------------------------------------------


def write_phantom(folder: Path) -> Path:
    (folder / "meshes").mkdir(parents=True)
    trimesh.creation.box(extents=(10.0, 10.0, 10.0)).export(folder / "meshes" / "step_00.ply")
    (folder / "phantom.json").write_text(
        json.dumps({"steps": [{"step": 0, "mesh": "meshes/step_00.ply"}]})
    )
    return folder


def write_step_dataset(folder: Path, seed: int = 1000) -> Path:
    (folder / "seq").mkdir(parents=True)
    (folder / "dataset.json").write_text(
        json.dumps({"sequences": [{"path": "seq", "phantom_seed": seed, "step": 0}]})
    )
    return folder


def test_step_dataset_phantom_folder_linking_out_is_refused(tmp_path: Path) -> None:
    ds = write_step_dataset(tmp_path / "ds")
    other = write_phantom(tmp_path / "other" / "phantoms" / "seed_1000")
    (ds / "phantoms").mkdir()
    (ds / "phantoms" / "seed_1000").symlink_to(other, target_is_directory=True)
    with pytest.raises(
        OutsideManifestError,
        match=re.escape("sequences[0].phantom_seed names 'phantoms/seed_1000'"),
    ):
        read_step_dataset([ds])
    # The dataset's own option allows it, as it allows a sequence folder elsewhere.
    (ref,) = read_step_dataset([ds], allow_outside=True)
    assert ref.phantom_dir == other.resolve()


def test_step_dataset_phantom_folder_inside_reads(tmp_path: Path) -> None:
    """Positive control: the phantom folder itself, inside the dataset, reads."""
    ds = write_step_dataset(tmp_path / "ds")
    phantom = write_phantom(ds / "phantoms" / "seed_1000")
    (ref,) = read_step_dataset([ds])
    assert ref.phantom_dir == phantom.resolve()
    assert len(phantom_step_mesh(ref.phantom_dir, 0).faces) == 12


def test_phantom_json_linking_to_another_phantoms_is_refused(tmp_path: Path) -> None:
    phantom = write_phantom(tmp_path / "ds" / "phantoms" / "seed_1000")
    other = write_phantom(tmp_path / "other" / "phantoms" / "seed_1000")
    (phantom / "phantom.json").unlink()
    (phantom / "phantom.json").symlink_to(other / "phantom.json")
    with pytest.raises(OutsideManifestError, match=re.escape("names 'phantom.json', which is")):
        phantom_step_mesh(phantom, 0)
    (phantom / "phantom.json").unlink()
    (phantom / "phantom.json").write_bytes((other / "phantom.json").read_bytes())
    assert len(phantom_step_mesh(phantom, 0).faces) == 12  # positive control


# --- 3. an NRRD header's data file ------------------------------------------------------

SHAPE = (8, 9, 10)


def raw_volume() -> bytes:
    """A label-like CT (air -1000 around a block of tissue 40), x fastest (NRRD order)."""
    d = np.full(SHAPE, -1000, np.int16)
    d[2:6, 2:7, 2:8] = 40
    return d.transpose(2, 1, 0).tobytes()


def nrrd_header(data_file: str) -> str:
    return (
        "NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\n"
        f"sizes: {SHAPE[0]} {SHAPE[1]} {SHAPE[2]}\n"
        "space directions: (1,0,0) (0,1,0) (0,0,1)\nspace origin: (0,0,0)\n"
        f"endian: little\nencoding: raw\ndata file: {data_file}\n"
    )


@pytest.fixture
def ct_dirs(tmp_path: Path) -> tuple[Path, Path]:
    """``ct/`` (where the header goes, with its own x.raw) and ``outside/x.raw``."""
    (tmp_path / "ct").mkdir()
    (tmp_path / "outside").mkdir()
    for folder in ("ct", "outside"):
        (tmp_path / folder / "x.raw").write_bytes(raw_volume())
        (tmp_path / folder / "x1.raw").write_bytes(raw_volume())
    return tmp_path / "ct", tmp_path / "outside"


# (header file name, data file field, offending name in the message); "{out}" is the
# outside folder's absolute path.
NRRD_CASES = [
    ("up.nhdr", "../outside/x.raw", "../outside/x.raw"),
    ("absolute.nhdr", "{out}/x.raw", "{out}/x.raw"),
    ("link.nhdr", "link.raw", "link.raw"),
    ("list.nhdr", "LIST 3\n../outside/x.raw", "../outside/x.raw"),
    ("numbered.nhdr", "../outside/x%d.raw 1 1 1 3", "../outside/x1.raw"),
    ("datafile.nrrd", "../outside/x.raw", "../outside/x.raw"),
]
# The same headers without the escape: the data beside the header.
NRRD_INSIDE = {
    "up.nhdr": "x.raw",
    "absolute.nhdr": "{ct}/x.raw",
    "link.nhdr": "inlink.raw",
    "list.nhdr": "LIST 3\nx.raw",
    "numbered.nhdr": "x%d.raw 1 1 1 3",
    "datafile.nrrd": "./x.raw",
}


@pytest.mark.parametrize(("name", "field", "shown"), NRRD_CASES, ids=[c[0] for c in NRRD_CASES])
def test_nrrd_data_file_outside_its_folder_is_refused(
    ct_dirs: tuple[Path, Path], name: str, field: str, shown: str
) -> None:
    ct, outside = ct_dirs
    (ct / "link.raw").symlink_to(outside / "x.raw")
    header = ct / name
    header.write_text(nrrd_header(field.format(out=outside)))
    pattern = re.escape(f"data file names '{shown.format(out=outside)}', which is {outside}")
    with pytest.raises(OutsideManifestError, match=pattern) as e:
        read_ct_volume(header)
    assert e.value.source == str(header) and "outside the header's folder" in str(e.value)
    with pytest.raises(OutsideManifestError, match=pattern):
        load_ct_surface(header)


@pytest.mark.parametrize("name", list(NRRD_INSIDE))
def test_nrrd_data_file_beside_its_header_reads(ct_dirs: tuple[Path, Path], name: str) -> None:
    """Positive control: the same header naming data inside its folder reads."""
    ct, _ = ct_dirs
    (ct / "inlink.raw").symlink_to("x.raw")
    header = ct / name
    header.write_text(nrrd_header(NRRD_INSIDE[name].format(ct=ct)))
    vol = read_ct_volume(header)
    assert vol.data.shape == SHAPE and vol.data.min() == -1000 and vol.data.max() == 40


def test_cli_ct_surface_refuses_an_nhdr_naming_data_outside_in_one_line(
    ct_dirs: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    ct, _ = ct_dirs
    (ct / "up.nhdr").write_text(nrrd_header("../outside/x.raw"))
    out = ct / "surface.ply"
    rc = chisel_main(["ct-surface", "--ct", str(ct / "up.nhdr"), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert "data file names '../outside/x.raw'" in err
    assert not out.exists()


# Found while fuzzing the header scan above: SimpleITK's NRRD reader crashes the process
# (SIGSEGV, exit 139) on a long header line it cannot parse and on a long data file path.
# Run in a child process, so that a crash fails the test instead of ending pytest.
LONG_LINES = {
    "long_data_file": "data file: " + "9" * 1200,
    "long_bad_labels": "data file: x.raw\nlabels: " + "9" * 1200,
    "lone_cr_splits_a_key_value": "data file: x.raw\nk:=" + "c" * 600 + "\r" + "c" * 1200,
}


@pytest.mark.parametrize("line", list(LONG_LINES.values()), ids=list(LONG_LINES))
def test_nrrd_header_that_crashed_simpleitk_is_one_line(
    ct_dirs: tuple[Path, Path], line: str
) -> None:
    import subprocess
    import sys

    ct, _ = ct_dirs
    header = ct / "long.nhdr"
    header.write_bytes(nrrd_header("x.raw").replace("data file: x.raw\n", line + "\n").encode())
    out = ct / "surface.ply"
    run = subprocess.run(
        [sys.executable, "-m", "chisel", "ct-surface", "--ct", str(header), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    err = run.stderr.strip()
    assert run.returncode == 1, (run.returncode, err[-300:])
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert f"{header}: " in err and "bytes" in err
    assert not out.exists()


def test_nrrd_header_with_long_comments_and_key_values_reads(ct_dirs: tuple[Path, Path]) -> None:
    """Positive control: long lines NrrdIO never refuses (comments, key:=value, content)."""
    ct, _ = ct_dirs
    extra = "# " + "a" * 3000 + "\nSegment0_Tags:=" + "b" * 3000 + "\ncontent: " + "c" * 3000
    header = ct / "long_ok.nhdr"
    header.write_text(nrrd_header("x.raw").replace("encoding: raw\n", f"encoding: raw\n{extra}\n"))
    assert read_ct_volume(header).data.shape == SHAPE


def test_the_commands_read_a_linked_sequence_only_with_their_flag(
    two_seqs: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``chisel render-depth`` and ``chisel update`` (its ``sequence:`` depth folder too)
    refuse a subfolder linked out of the sequence folder and read it given
    --allow-outside-sequence."""
    seq, other = two_seqs
    replace_by_link(seq / "mask", other / "mask")
    mesh = tmp_path / "plane.ply"
    trimesh.creation.box(extents=(40.0, 40.0, 1.0)).apply_translation((0, 0, 30)).export(mesh)
    render = ["render-depth", "--mesh", str(mesh), "--sequence", str(seq)]
    assert chisel_main([*render, "--out", str(tmp_path / "r1")]) == 1
    assert "--allow-outside-sequence" in capsys.readouterr().err
    assert not (tmp_path / "r1").exists()
    assert chisel_main([*render, "--out", str(tmp_path / "r2"), "--allow-outside-sequence"]) == 0
    model = tmp_path / "m0.npz"
    build = ["build", "--surface", str(mesh), "--sequence", str(seq), "--out", str(model)]
    assert chisel_main([*build, "--no-progress"]) == 1
    assert not model.exists()
    assert chisel_main([*build, "--no-progress", "--allow-outside-sequence"]) == 0
    update = ["update", "--model", str(model), "--sequence", str(tmp_path / "r2"), "--no-progress"]
    depth = ["--depth-source", f"sequence:{seq}", "--no-registration"]
    assert chisel_main([*update, "--out", str(tmp_path / "m1.npz"), *depth]) == 1
    assert "'mask'" in capsys.readouterr().err
    assert not (tmp_path / "m1.npz").exists()
    out = tmp_path / "m2.npz"
    assert chisel_main([*update, "--out", str(out), *depth, "--allow-outside-sequence"]) == 0
