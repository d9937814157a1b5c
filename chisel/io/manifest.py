"""Paths named inside a manifest (``input.json``, ``phantom.json``, ...) and the JSON itself.

A manifest is data from elsewhere: it may name ``../../../../etc/shadow`` or a link to
another patient's folder. Every path it names goes through :func:`named_path`, which
resolves it (links and ``..`` followed) and refuses one outside the manifest's own folder
unless the user allowed that explicitly (``--allow-outside-manifest``). Each caller then
checks the file's kind (a mesh parses as a mesh, poses as poses) before it reads or copies
it, so nothing is copied byte for byte that was not understood first.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Literal

from chisel.core.errors import InvalidInputError, OutsideManifestError, ResourceLimitError

MAX_MANIFEST_BYTES = 16 * 2**20
"""Largest manifest (JSON) read; real ones are a few kB (a phantom's airway path ~100 kB)."""

MAX_JSON_DEPTH = 64
"""Deepest nesting accepted in a manifest; deeper JSON is refused before Python's own
recursion limit would turn it into a traceback."""

ALLOW_OUTSIDE_OPTION = "--allow-outside-manifest"
"""The command-line option that lets a manifest name files outside its folder."""


def _depth(text: str) -> int:
    """Deepest bracket nesting of JSON ``text`` (brackets inside strings skipped)."""
    deepest = level = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            level += 1
            deepest = max(deepest, level)
        elif ch in "]}":
            level -= 1
    return deepest


def json_type(value: object) -> str:
    """JSON's name for ``value``'s type, for messages about a hand-edited file."""
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int | float):
        return "a number"
    names: dict[type, str] = {dict: "an object", list: "an array", str: "a string"}
    return names.get(type(value), "null")


def read_json_manifest(
    path: str | Path, error: type[InvalidInputError] = InvalidInputError
) -> dict[str, Any]:
    """Read a JSON object from ``path``; every failure is one ``error`` naming the file.

    Refused: a missing or unreadable file, one over :data:`MAX_MANIFEST_BYTES`, text that
    is not UTF-8 or not JSON, nesting deeper than :data:`MAX_JSON_DEPTH`, and a top level
    that is not an object. NaN/Infinity literals (which Python writes) are read; each
    field's own check refuses them where a finite number is needed.
    """
    data = read_json_value(path, error)
    if not isinstance(data, dict):
        raise error(Path(path), f"expected a JSON object, got {json_type(data)}")
    return data


def read_json_value(path: str | Path, error: type[InvalidInputError] = InvalidInputError) -> Any:
    """Any JSON value from ``path`` (a list, for a bite plan), read and refused as
    :func:`read_json_manifest` reads and refuses, but whatever its top level."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise error(path, f"cannot read: {exc.strerror or exc}") from None
    if not path.is_file():
        raise error(path, "is not a file")
    if size > MAX_MANIFEST_BYTES:
        raise error(path, f"is {size} bytes; a manifest is at most {MAX_MANIFEST_BYTES} bytes")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise error(path, f"cannot read: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(path, f"not a text file (invalid UTF-8 at byte {exc.start})") from None
    return parse_json_text(path, text, error)


def parse_json_text(
    source: str | Path,
    text: str,
    error: type[InvalidInputError] = InvalidInputError,
    what: str = "",
) -> Any:
    """Any JSON value from ``text`` (read from ``source``; ``what`` names a member of it),
    refused as :func:`read_json_value` refuses it: nesting deeper than
    :data:`MAX_JSON_DEPTH` (checked before the parser recurses), text that is not JSON."""
    prefix = f"{what}: " if what else ""
    if _depth(text) > MAX_JSON_DEPTH:
        raise error(Path(source), f"{prefix}JSON nested deeper than {MAX_JSON_DEPTH} levels")
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise error(Path(source), f"{prefix}invalid JSON: {exc}") from None


def named_path(
    manifest: str | Path,
    value: object,
    key: str,
    *,
    allow_outside: bool = False,
    kind: Literal["file", "folder", "any"] = "any",
    base: str | Path | None = None,
    option: str = ALLOW_OUTSIDE_OPTION,
) -> Path:
    """The resolved path that ``manifest`` names with ``value`` under ``key``.

    ``value`` must be a non-empty string; relative to ``base`` (default: the manifest's
    folder). The result, links and ``..`` resolved, must lie inside the manifest's folder
    (itself resolved) unless ``allow_outside``: raises :class:`OutsideManifestError`
    naming the manifest, the key and ``option``. ``kind`` "file"/"folder" also requires
    that it exists as one (:class:`InvalidInputError`).
    """
    manifest = Path(manifest)
    if not isinstance(value, str) or not value or "\x00" in value:
        raise InvalidInputError(manifest, f"{key}: expected a file path, got {value!r}"[:300])
    root = manifest.absolute().parent.resolve()
    start = Path(base) if base is not None else root
    try:
        resolved = (start / os.path.expanduser(value)).resolve()
    except (OSError, RuntimeError, ValueError) as exc:  # a link loop, an unencodable name
        raise InvalidInputError(manifest, f"{key}: cannot resolve {value!r}: {exc}") from None
    if not allow_outside and resolved != root and root not in resolved.parents:
        raise OutsideManifestError(
            manifest,
            f"{key} names {value!r}, which is {resolved}, outside the manifest's folder "
            f"{root}; a manifest may only name files beside it (pass {option} if this "
            "dataset really keeps its data elsewhere)",
        )
    if kind == "file" and not resolved.is_file():
        raise InvalidInputError(manifest, f"{key}: {resolved} is not a file (or is missing)")
    if kind == "folder" and not resolved.is_dir():
        raise InvalidInputError(manifest, f"{key}: {resolved} is not a folder (or is missing)")
    return resolved


def check_inside(
    manifest: str | Path,
    path: Path,
    what: str,
    *,
    allow_outside: bool = False,
    option: str = ALLOW_OUTSIDE_OPTION,
) -> Path:
    """Resolve ``path`` (found by listing a folder the manifest names, e.g. one image) and
    refuse it outside the manifest's folder, as :func:`named_path` does: a link inside an
    accepted folder may still point anywhere."""
    return named_path(manifest, str(path), what, allow_outside=allow_outside, option=option)


def check_size(source: str | Path, what: str, count: int, limit: int) -> None:
    """Raise :class:`ResourceLimitError` if a declared ``count`` exceeds ``limit``."""
    if count > limit:
        raise ResourceLimitError(source, f"{what} is {count}, over the limit of {limit}")
