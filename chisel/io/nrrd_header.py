"""NRRD headers read before SimpleITK sees them: the data files a header names must lie
beside it (an ``.nhdr`` may name ``../../other/ct.raw`` or an absolute path, and SimpleITK
would read it), and no header line may be one that crashes SimpleITK's reader."""

from __future__ import annotations

import os
import re
from pathlib import Path

from chisel.core.errors import InvalidInputError, OutsideManifestError, ResourceLimitError
from chisel.io.manifest import MAX_MANIFEST_BYTES, check_size, named_path

MAX_NRRD_DATA_FILES = 65536
"""Most detached data files one NRRD header may name (a CT kept as one file per slice has
a few thousand)."""
_NRRD_DATA_FILE_FIELDS = ("data file", "datafile")
MAX_NRRD_FIELD_LINE = 960
"""Longest NRRD header line (and data file path, folder included) read, but for comments,
``key:=value`` lines and ``content``: SimpleITK 2.5's NRRD reader (ITK 5.4) crashes the
process (SIGSEGV) on a line of ~1000 bytes that it cannot parse (its error message quotes
the line) and on a data file path of ~990. Real ones are under 300 bytes."""
_NRRD_FIELDS = frozenset(
    (
        "type", "dimension", "space", "space dimension", "spacedimension", "sizes",
        "spacings", "thicknesses", "axis mins", "axismins", "axis maxs", "axismaxs",
        "space directions", "spacedirections", "centers", "centerings", "kinds", "min",
        "max", "old min", "oldmin", "old max", "oldmax", "endian", "encoding", "line skip",
        "lineskip", "byte skip", "byteskip", "block size", "blocksize", "number",
        "space origin", "spaceorigin", "measurement frame", "measurementframe", "content",
        "labels", "units", "space units", "spaceunits", "sample units", "sampleunits",
        *_NRRD_DATA_FILE_FIELDS,
    )
)  # fmt: skip
"""The NRRD field names (NrrdIO's, either spelling); other ``name: value`` lines are
``key:=value`` pairs or errors."""


_NRRD_EOL = re.compile(rb"\r\n|\r|\n")
"""NrrdIO's line ends: a lone ``\\r`` ends a line too."""


def _nrrd_header_lines(path: Path) -> list[str]:
    """The lines of an NRRD header after its magic line, split as NrrdIO splits them, up to
    the blank line that ends it (attached data follows) or the end of a detached header;
    [] for a file that does not start with the NRRD magic (SimpleITK refuses it). Bytes
    that are not UTF-8 are kept (surrogate escapes), so a file name is checked as the reader
    will open it."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(MAX_MANIFEST_BYTES + 1)
    except OSError as exc:
        raise InvalidInputError(path, f"cannot read: {exc.strerror or exc}") from None
    if not head.startswith(b"NRRD"):
        return []
    lines: list[str] = []
    pos = 0
    while (end := _NRRD_EOL.search(head, pos)) is not None or pos < len(head):
        stop = end.start() if end is not None else len(head)
        if stop == pos:
            return lines[1:]  # a blank line (or the end of the file) ends the header
        if end is None and len(head) > MAX_MANIFEST_BYTES:
            raise ResourceLimitError(
                path, f"NRRD header runs past {MAX_MANIFEST_BYTES} bytes without its end"
            )
        lines.append(head[pos:stop].decode("utf-8", "surrogateescape"))
        pos = end.end() if end is not None else len(head)
    return lines[1:]


def _nrrd_numbered(template: str, n: int) -> str:
    """``template``'s C conversion ``%d`` / ``%5d`` / ``%05d`` filled with ``n`` (``%%`` is a
    percent sign), as NrrdIO's ``sprintf`` makes a numbered data file's name. A width is
    capped at 255 (the most a file name holds: a wider one cannot be opened anyway)."""

    def fill(m: re.Match[str]) -> str:
        if m.group(0) == "%%":
            return "%"
        digits = m.group(1).lstrip("0")
        width = 255 if len(digits) > 3 else min(int(digits or 0), 255)
        return format(n, f"{'0' if m.group(1).startswith('0') else ''}{width}d")

    return re.sub(r"%%|%(\d*)d", fill, template)


def _nrrd_is_numbered(value: str) -> bool:
    """NrrdIO's test for the ``<template> <min> <max> <step>`` form: the first ``%`` that is
    not ``%%`` starts a ``%d`` conversion (digits allowed in between)."""
    m = re.match(r"(?:[^%]|%%)*%\d*(.)", value)
    return m is not None and m.group(1) == "d"


def _nrrd_data_files(path: Path, lines: list[str]) -> list[str]:
    """The file names an NRRD header's ``data file:`` field makes NrrdIO open (relative to
    the header's folder unless absolute): one name, the lines after ``LIST``, or every
    number of ``<template> <min> <max> <step>``; [] for attached data. Every such field is
    taken (NrrdIO refuses a repeated one; taking all cannot miss the one it reads)."""
    names: list[str] = []
    for k, line in enumerate(lines):
        key, sep, value = line.partition(": ")
        if line.startswith("#") or not sep or key.strip().lower() not in _NRRD_DATA_FILE_FIELDS:
            continue
        value = value.lstrip(" \t")
        if _nrrd_is_numbered(value):
            names += _nrrd_numbered_names(path, value)
        elif value.startswith("LIST"):
            return names + lines[k + 1 :]  # every line after it names a file
        else:
            names.append(value)
    return names


def _nrrd_numbered_names(path: Path, value: str) -> list[str]:
    """The names ``<template> <min> <max> <step>`` stands for (NrrdIO counts from min to
    max inclusive); just ``template`` at min where NrrdIO refuses the numbers."""
    template, rest = value, ""
    if (cut := re.search(r"[ \t]", value)) is not None:
        template, rest = value[: cut.start()], value[cut.start() :]
    nums = re.match(r"\s*([+-]?\d+)\s*([+-]?\d+)\s*([+-]?\d+)", rest)
    if nums is None:
        return [_nrrd_numbered(template, 0)]
    if any(len(x.lstrip("+-")) > 9 for x in nums.groups()):  # C int overflow: undefined
        raise InvalidInputError(path, f"data file numbers out of range: {rest.strip()[:80]!r}")
    lo, hi, step = (int(x) for x in nums.groups())
    if step == 0 or (hi - lo) * step < 0:
        return [_nrrd_numbered(template, lo)]
    check_size(path, "number of NRRD data files", (hi - lo) // step + 1, MAX_NRRD_DATA_FILES)
    return [_nrrd_numbered(template, n) for n in range(lo, hi + (1 if step > 0 else -1), step)]


def _nrrd_line_may_crash(line: str) -> bool:
    """Whether NrrdIO may quote a long ``line`` in an error message (all but a comment, a
    ``key:=value`` pair and ``content``, which it never refuses)."""
    if line.startswith("#"):
        return False
    key, sep, _ = line.partition(": ")
    if sep and key.strip().lower() in _NRRD_FIELDS:
        return key.lower() != "content"
    return ":=" not in line


def check_nrrd_data_files(path: str | Path) -> None:
    """Refuse an NRRD header (``.nhdr``, or a ``.nrrd`` with a ``data file:`` field) that
    names a data file outside its own folder (``../../other/ct.raw``, an absolute path, a
    link that points out): SimpleITK would read it. Raises :class:`OutsideManifestError`
    naming the header, the name and where it leads; :class:`InvalidInputError` for a field
    line or data file path past :data:`MAX_NRRD_FIELD_LINE` (SimpleITK would crash)."""
    path = Path(path)
    root = path.absolute().parent.resolve()
    lines = _nrrd_header_lines(path)
    for k, line in enumerate(lines, 2):
        size = len(line.encode("utf-8", "surrogateescape"))
        if size > MAX_NRRD_FIELD_LINE and _nrrd_line_may_crash(line):
            raise InvalidInputError(
                path,
                f"header line {k} is {size} bytes, over the {MAX_NRRD_FIELD_LINE} read "
                "(SimpleITK's NRRD reader crashes on a longer line it cannot parse)",
            )
    for name in _nrrd_data_files(path, lines):
        full = os.path.join(os.path.dirname(str(path)), name)  # as NrrdIO forms it
        if len(full.encode("utf-8", "surrogateescape")) > MAX_NRRD_FIELD_LINE:
            raise InvalidInputError(
                path,
                f"data file {name[:60]!r}... makes a path over {MAX_NRRD_FIELD_LINE} bytes "
                "(SimpleITK's NRRD reader crashes on a longer one)",
            )
        # NrrdIO does not expand "~"; named_path would.
        value = f"./{name}" if name.startswith("~") else name
        resolved = named_path(path, value, "data file", allow_outside=True)
        if resolved != root and root not in resolved.parents:
            raise OutsideManifestError(
                path,
                f"data file names {name!r}, which is {resolved}, outside the header's folder "
                f"{root}; an NRRD header may only name data files beside it (move the data "
                "file into the header's folder)",
            )
