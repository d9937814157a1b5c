"""Fuzzing the readers of files from elsewhere (issue 17): sequence.json, poses.txt,
phantom.json, input.json and model .npz.

For any input a reader either returns or raises one of the project's errors whose message
names a file in the folder it was given; it never crashes with another exception, never
allocates past a limit (numpy's allocations are traced by tracemalloc) and never opens a
file outside that folder (an audit hook records every ``open``). Few examples, so that it
stays well under a minute in CI; the strategies mutate valid files, where bugs hide.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import sys
import tempfile
import tracemalloc
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from chisel.core.errors import ChiselError
from chisel.core.geometry import Camera, look_at
from chisel.io.import_reference import import_reference
from chisel.io.sequence import Frame, Sequence, write_sequence
from chisel.model import TsdfModel
from sim.phantom import load_phantom

FUZZ = settings(
    max_examples=25,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
    derandomize=True,
)
PEAK_LIMIT_BYTES = 256 * 2**20
CAM = Camera.from_fov(16, 12, 70)

_opened: list[str] = []
_watching = [False]  # an audit hook cannot be removed: it records only inside _watched


def _audit(event: str, args: tuple[Any, ...]) -> None:
    if _watching[0] and event == "open" and args and isinstance(args[0], str | bytes):
        _opened.append(os.fsdecode(args[0]))


sys.addaudithook(_audit)


@contextlib.contextmanager
def _watched(outside: Path) -> Iterator[None]:
    """Record opens and numpy allocations in the block; fail on either rule."""
    _opened.clear()
    tracemalloc.start()
    _watching[0] = True
    try:
        yield
    finally:
        _watching[0] = False
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        touched = [p for p in _opened if str(outside) in os.path.realpath(p)]
        _opened.clear()
        assert not touched, f"a reader opened a file outside its folder: {touched}"
        assert peak < PEAK_LIMIT_BYTES, f"a reader allocated {peak} bytes"


def _refused_or_read(read: Callable[[], object], folder: Path) -> None:
    """Run ``read``; a refusal must be a ChiselError that names a file in ``folder``."""
    try:
        read()
    except ChiselError as exc:
        assert str(folder) in str(exc), f"the error does not name the file: {exc}"


# ------------------------------------------------------------------------ strategies

_paths = st.sampled_from(
    ["../outside/secret.ply", "/etc/passwd", "seg.ply", "", ".", "..", "a\x00b", "images"]
)
_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(10**30), 10**30),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    _paths,
)
_values = st.recursive(
    _scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=6), inner, max_size=5)
    ),
    max_leaves=12,
)


def _mutate(doc: dict[str, Any], keys: list[str], data: st.DataObject) -> dict[str, Any]:
    """Replace or delete a few (possibly nested, dotted) keys of a valid document."""
    doc = json.loads(json.dumps(doc))
    for _ in range(data.draw(st.integers(1, 3))):
        key = data.draw(st.sampled_from(keys))
        *head, last = key.split(".")
        target: Any = doc
        for part in head:
            if isinstance(target, dict):
                target = target.get(part)
            elif isinstance(target, list) and part.isdigit() and int(part) < len(target):
                target = target[int(part)]
            else:
                target = None
        if isinstance(target, dict):
            if data.draw(st.booleans()):
                target.pop(last, None)
            else:
                target[last] = data.draw(_values)
        elif isinstance(target, list) and last.isdigit() and int(last) < len(target):
            target[int(last)] = data.draw(_values)
    return doc


def _json_bytes(doc: Any, data: st.DataObject) -> bytes:
    text = json.dumps(doc, allow_nan=True).encode()
    how = data.draw(st.sampled_from(["as is", "cut", "junk", "deep"]))
    if how == "cut":
        return text[: data.draw(st.integers(0, len(text)))]
    if how == "junk":
        return data.draw(st.binary(max_size=64)) + text
    if how == "deep":
        n = data.draw(st.integers(100, 100000))
        return b"[" * n + b"]" * n
    return text


# --------------------------------------------------------------------- sequence folders


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("fuzz")
    (root / "outside").mkdir()
    trimesh.creation.box(extents=(5.0, 5.0, 5.0)).export(root / "outside" / "secret.ply")
    rng = np.random.default_rng(0)
    frames = [
        Frame(
            i,
            look_at([i, 0.0, 0.0], [i, 0.0, 30.0], up=[0, -1, 0]),
            rng.integers(0, 255, (*CAM.shape, 3), dtype=np.uint8),
            rng.uniform(5, 20, CAM.shape).astype(np.float32),
            rng.random(CAM.shape) > 0.2,
        )
        for i in range(2)
    ]
    write_sequence(root / "seq", CAM, frames, camera_mask=np.ones(CAM.shape, bool))
    return root


def _work(base: Path, what: str) -> tuple[Path, Path]:
    """A fresh copy of ``base/what`` inside a new folder beside ``base/outside``."""
    work = Path(tempfile.mkdtemp(dir=base))
    if (base / what).exists():
        shutil.copytree(base / what, work / what)
    return work, work / what


_HEADER_KEYS = [
    "format", "version", "num_frames", "camera", "camera.width", "camera.height",
    "camera.K", "camera.dist", "undistorted", "units", "depth_kind", "has_rgb", "has_depth",
    "has_mask", "has_true_poses", "has_camera_mask", "meta",
]  # fmt: skip


@FUZZ
@given(data=st.data())
def test_sequence_json(base: Path, data: st.DataObject) -> None:
    work, seq = _work(base, "seq")
    header = json.loads((seq / "sequence.json").read_text())
    (seq / "sequence.json").write_bytes(_json_bytes(_mutate(header, _HEADER_KEYS, data), data))
    with _watched(base / "outside"):
        _refused_or_read(lambda: list(Sequence(seq)), seq)
    shutil.rmtree(work)


_pose_lines = st.lists(
    st.lists(
        st.one_of(
            st.floats(allow_nan=True, allow_infinity=True, width=32).map(repr),
            st.sampled_from(["1", "0", "x", "", "1e400", "#"]),
        ),
        max_size=20,
    ).map(" ".join),
    max_size=4,
).map("\n".join)


@FUZZ
@given(text=_pose_lines, raw=st.binary(max_size=40), use_raw=st.booleans())
def test_poses_txt(base: Path, text: str, raw: bytes, use_raw: bool) -> None:
    work, seq = _work(base, "seq")
    (seq / "poses.txt").write_bytes(raw if use_raw else text.encode())
    with _watched(base / "outside"):
        _refused_or_read(lambda: Sequence(seq), seq)
    shutil.rmtree(work)


# ---------------------------------------------------------------------- phantom.json

_PHANTOM = {
    "format": "endoscopic-chisel/phantom",
    "version": 1,
    "seed": 0,
    "steps": [{"step": 0, "name": "preop", "mesh": "m.ply"}],
    "roi_box_mm": [[0, 0, 0], [1, 1, 1]],
    "target": {"name": "t", "center_mm": [0, 0, 0], "normal": [0, 0, 1]},
    "airway_path_mm": [[0, 0, 0], [1, 1, 1]],
}
_PHANTOM_KEYS = [
    "format", "version", "seed", "steps", "steps.0", "steps.0.step", "steps.0.mesh",
    "roi_box_mm", "target", "target.center_mm", "target.normal", "airway_path_mm",
]  # fmt: skip


@FUZZ
@given(data=st.data())
def test_phantom_json(base: Path, data: st.DataObject) -> None:
    work = Path(tempfile.mkdtemp(dir=base))
    ph = work / "ph"
    ph.mkdir()
    (ph / "phantom.json").write_bytes(_json_bytes(_mutate(_PHANTOM, _PHANTOM_KEYS, data), data))
    with _watched(base / "outside"):
        _refused_or_read(lambda: load_phantom(ph), ph)
    shutil.rmtree(work)


# ------------------------------------------------------------------------ input.json

_INPUT = {
    "intrinsics": "14,14,7.5,5.5",
    "steps": 0,
    "preop_data": {"base_dir": "preop", "seg": "seg.ply", "poses": "trajectories.npy"},
}
_INPUT_KEYS = [
    "intrinsics", "steps", "preop_data", "preop_data.base_dir", "preop_data.seg",
    "preop_data.poses", "preop_data.img_dir", "preop_data.start_idx", "1",
]  # fmt: skip


@FUZZ
@given(data=st.data())
def test_input_json(base: Path, data: st.DataObject) -> None:
    work = Path(tempfile.mkdtemp(dir=base))
    ds = work / "ds"
    (ds / "preop" / "images").mkdir(parents=True)
    # Links that lead out: a reader must resolve them before opening anything.
    (ds / "preop" / "seg.ply").symlink_to(base / "outside" / "secret.ply")
    np.save(ds / "preop" / "trajectories.npy", np.tile(np.eye(4), (1, 1, 1)))
    (ds / "input.json").write_bytes(_json_bytes(_mutate(_INPUT, _INPUT_KEYS, data), data))
    with _watched(base / "outside"):
        _refused_or_read(lambda: import_reference(ds / "input.json", work / "out"), ds)
    assert not (work / "out").exists()
    shutil.rmtree(work)


# ------------------------------------------------------------------------ model .npz


def _model_fields() -> dict[str, np.ndarray]:
    T = np.diag([0.5, 0.5, 0.5, 1.0])
    return {
        "format": np.array("endoscopic-chisel/model"),
        "version": np.array(1),
        "tsdf": np.zeros((3, 3, 3), np.float32),
        "weight": np.zeros((3, 3, 3), np.float32),
        "T_world_from_voxel": T,
        "voxel_size_mm": np.array(0.5),
        "trunc_mm": np.array(2.0),
        "step": np.array(0),
    }


_arrays = st.one_of(
    st.sampled_from(
        [
            np.array(np.nan),
            np.array(1e300),
            np.array(1e-300),
            np.array(-1),
            np.array("x"),
            np.zeros((2, 2)),
            np.zeros((3, 3, 3), np.float64),
            np.full((3, 3, 3), 5.0, np.float32),
            np.zeros(0),
        ]
    ),
    st.floats(allow_nan=True, allow_infinity=True).map(np.array),
)


@FUZZ
@given(
    data=st.data(),
    cut=st.one_of(st.none(), st.integers(0, 2000)),
)
def test_model_npz(base: Path, data: st.DataObject, cut: int | None) -> None:
    fields = _model_fields()
    for _ in range(data.draw(st.integers(0, 3))):
        key = data.draw(st.sampled_from(sorted(fields)))
        if data.draw(st.booleans()):
            fields.pop(key, None)
        else:
            fields[key] = data.draw(_arrays)
    buf = io.BytesIO()
    np.savez_compressed(buf, **fields)
    raw = buf.getvalue()
    work = Path(tempfile.mkdtemp(dir=base))
    path = work / "m.npz"
    path.write_bytes(raw if cut is None else raw[:cut])
    with _watched(base / "outside"):
        _refused_or_read(lambda: TsdfModel.load(path), work)
    shutil.rmtree(work)


# ---------------------------------------------------------------------- NIfTI headers

_shorts = st.one_of(
    st.sampled_from([-32768, -1, 0, 1, 2, 3, 4, 5, 7, 8, 16, 100, 2000, 32767]),
    st.integers(-32768, 32767),
)
_floats = st.one_of(
    st.sampled_from([0.0, -1.0, 1e-30, 1e30, 3.4e38, float("nan"), float("inf"), -float("inf")]),
    st.floats(width=32, allow_nan=True, allow_infinity=True),
)
# The NIfTI data type codes (2 uint8 ... 128 RGB, 1792 complex128, 2304 RGBA) and others.
_datatypes = st.sampled_from(
    [2, 4, 8, 16, 32, 64, 128, 256, 512, 768, 1024, 1280, 1536, 1792, 2048, 2304, 0, 1, -1]
)
_NIFTI_FIELDS: dict[str, tuple[int, str, st.SearchStrategy[Any]]] = {
    # name: (offset in the NIfTI-1 header, struct format, values a broken file holds)
    "sizeof_hdr": (0, "<i", st.sampled_from([348, 540, 0, -1, 2**31 - 1])),
    **{f"dim{i}": (40 + 2 * i, "<h", _shorts) for i in range(5)},
    "datatype": (70, "<h", _datatypes),
    "bitpix": (72, "<h", _shorts),
    **{f"pixdim{i}": (76 + 4 * i, "<f", _floats) for i in range(4)},
    "vox_offset": (108, "<f", _floats),
    "scl_slope": (112, "<f", _floats),
    "scl_inter": (116, "<f", _floats),
    "xyzt_units": (123, "<B", st.integers(0, 255)),
    "qform_code": (252, "<h", _shorts),
    "sform_code": (254, "<h", _shorts),
    "quatern_b": (256, "<f", _floats),
    "quatern_d": (264, "<f", _floats),
    "qoffset_x": (268, "<f", _floats),
    "srow_x0": (280, "<f", _floats),
    "srow_x3": (292, "<f", _floats),
    "srow_y1": (300, "<f", _floats),
    "srow_z2": (320, "<f", _floats),
}


@pytest.fixture(scope="module")
def nifti_raw() -> bytes:
    """A small valid NIfTI-1 (uncompressed bytes): a 4x5x6 int16 label volume, sform set."""
    from chisel.io.ct import nifti_bytes

    data = np.zeros((4, 5, 6), np.int16)
    data[1:3, 1:4, 2:5] = 1
    return nifti_bytes(data, np.diag([0.5, 0.6, 0.7, 1.0]), compress=False)


@settings(FUZZ, max_examples=int(os.environ.get("NIFTI_FUZZ_EXAMPLES", "60")))
@given(data=st.data())
def test_nifti_header(base: Path, nifti_raw: bytes, data: st.DataObject) -> None:
    import gzip
    import struct

    from chisel.io.ct import read_ct_volume

    raw = bytearray(nifti_raw)
    names = data.draw(st.lists(st.sampled_from(sorted(_NIFTI_FIELDS)), min_size=1, max_size=4))
    # The data type is where readers break (RGB, complex voxels): change it more often.
    for name in names + ["datatype"] * data.draw(st.integers(0, 1)):
        offset, fmt, values = _NIFTI_FIELDS[name]
        struct.pack_into(fmt, raw, offset, data.draw(values))
    # Cut the file, or pad it so that a wider datatype or a larger dim still finds data.
    cut = data.draw(st.one_of(st.none(), st.none(), st.integers(0, len(raw))))
    pad = data.draw(st.sampled_from([0, 240, 4096]))
    body = bytes(raw if cut is None else raw[:cut]) + bytes(pad)
    compressed = data.draw(st.booleans())
    work = Path(tempfile.mkdtemp(dir=base))
    path = work / ("ct.nii.gz" if compressed else "ct.nii")
    path.write_bytes(gzip.compress(body, mtime=0) if compressed else body)
    with _watched(base / "outside"):
        _refused_or_read(lambda: read_ct_volume(path), work)
    shutil.rmtree(work)
