"""Typed configuration: frozen dataclasses are the one home of every parameter.

A configuration is a frozen dataclass whose fields carry a type annotation, a default and
a docstring (the string literal right after the field). From that one definition this
module derives everything else:

* :func:`check_fields` checks each field against its annotation (call it first in
  ``__post_init__``), so YAML files, CLI flags and direct construction are checked alike;
* :func:`config_from_dict` / :func:`load_config_file` build a (nested) configuration
  from a mapping or a YAML file, refusing unknown keys and values of the wrong kind with an
  error that names the file and the dotted key;
* :func:`add_config_arguments` / :func:`config_from_args` turn the fields into
  ``argparse`` flags (help text = the field's docstring, default = the field's default)
  and back;
* :func:`config_to_dict` / :func:`replace_in` write a configuration out and change it
  by dotted keys.

Values are never converted between kinds: YAML ``2.5`` for an integer, ``"85"`` for a
number or ``"no"`` for a boolean are errors, not guesses.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import math
import numbers
import textwrap
import types
import typing
from collections.abc import Iterable
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
import yaml

from chisel.core.errors import ConfigError, InvalidInputError

C = TypeVar("C")

MAX_CONFIG_BYTES = 1 << 20
"""Largest configuration file read, bytes: a configuration is a page of text."""


def show(value: Any) -> str:
    """A short, YAML-flavoured description of a value for error messages."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f"{value!r} (a string)"
    text = repr(value.tolist() if isinstance(value, np.ndarray) else value)
    return text if len(text) <= 60 else text[:57] + "..."


def _require(cond: bool, key: str, problem: str, error: type[ConfigError]) -> None:
    if not cond:
        raise error(key, problem)


def is_integer(value: Any) -> bool:
    """Whether ``value`` is an integer (Python's or numpy's), not a bool or a float that
    happens to be whole: what an ``int`` field, a seed or a count read from a file must be."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool | np.bool_)


def check_value(value: Any, tp: Any, key: str, error: type[ConfigError] = ConfigError) -> Any:
    """``value`` checked against the annotation ``tp``; returns it normalised.

    Normalisation only makes equal values uniform (lists -> tuples, numpy scalars ->
    Python numbers); it never converts between kinds.
    """
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in args if a is not type(None)]
        if value is None and len(options) < len(args):
            return None
        if len(options) != 1:  # a programming error: only ``X | None`` is supported
            raise TypeError(f"{key}: unsupported union {tp!r}")
        return check_value(value, options[0], key, error)
    if origin is Literal:
        _require(
            isinstance(value, str) and value in args,
            key,
            f"expected one of {', '.join(map(str, args))}, got {show(value)}",
            error,
        )
        return value
    if origin is tuple:
        variadic = len(args) == 2 and args[1] is Ellipsis
        noun = "numbers" if all(a is float for a in args if a is not Ellipsis) else "values"
        what = f"a list of {noun}" if variadic else f"a list of {len(args)} {noun}"
        _require(
            isinstance(value, list | tuple | np.ndarray) and not isinstance(value, str),
            key,
            f"expected {what}, got {show(value)}",
            error,
        )
        items = list(value)
        _require(
            variadic or len(items) == len(args),
            key,
            f"expected {what}, got {len(items)}: {show(items)}",
            error,
        )
        elem_types = [args[0]] * len(items) if variadic else list(args)
        return tuple(
            check_value(v, t, f"{key}[{i}]", error)
            for i, (v, t) in enumerate(zip(items, elem_types, strict=True))
        )
    if tp is bool:
        # Not ``bool(value)``: the string "no" would be true.
        _require(
            isinstance(value, bool | np.bool_),
            key,
            f"expected true or false, got {show(value)}",
            error,
        )
        return bool(value)
    if tp is int:
        _require(
            is_integer(value),
            key,
            f"expected an integer, got {show(value)}",
            error,
        )
        return int(value)
    if tp is float:
        _require(
            isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_),
            key,
            f"expected a number, got {show(value)}",
            error,
        )
        try:
            finite = math.isfinite(value)
        except OverflowError:  # an integer too large for a float
            finite = False
        _require(finite, key, f"expected a finite number, got {show(value)}", error)
        # Keep Python ints as given (manifests record the configuration as written).
        return value if type(value) in (int, float) else float(value)
    if isinstance(tp, type) and is_dataclass(tp):
        _require(
            isinstance(value, tp),
            key,
            f"expected a mapping of {tp.__name__} keys, got {show(value)}",
            error,
        )
        return value
    if tp is str:
        _require(isinstance(value, str), key, f"expected a string, got {show(value)}", error)
        return value
    raise TypeError(f"{key}: unsupported field type {tp!r}")  # a programming error


@functools.cache
def field_types(cls: type) -> dict[str, Any]:
    """The resolved annotations of a dataclass's fields."""
    return typing.get_type_hints(cls)


def check_ranges(obj: Any, section: str, checks: Iterable[tuple[str, bool, str]]) -> None:
    """Raise :class:`ConfigError` for the first ``(field, ok, expected)`` of ``checks`` that
    is not ok, naming the dotted key (``section.field``; ``section`` may be "") and the
    value ``obj`` holds: "must be <expected>, got <value>"."""
    for name, ok, expected in checks:
        if not ok:
            key = f"{section}.{name}" if section else name
            raise ConfigError(key, f"must be {expected}, got {getattr(obj, name)}")


def check_fields(obj: Any, section: str = "", error: type[ConfigError] = ConfigError) -> None:
    """Check every field of the frozen dataclass ``obj`` against its annotation.

    Call it first in ``__post_init__``; the error names the dotted key (``section.field``).
    """
    hints = field_types(type(obj))  # type: ignore[arg-type]  # classes are hashable
    for f in fields(obj):
        key = f"{section}.{f.name}" if section else f.name
        value = getattr(obj, f.name)
        checked = check_value(value, hints[f.name], key, error)
        if checked is not value:
            object.__setattr__(obj, f.name, checked)


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """Each field's docstring (the string literal after it in the class body), one line."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError):  # no source (e.g. frozen into a binary)
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node, nxt in zip(body, body[1:], strict=False):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)
            ):
                docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


def _default_of(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _tupleize(value: Any) -> Any:
    if isinstance(value, list):
        return tuple(_tupleize(v) for v in value)
    return value


def config_from_dict(
    cls: type[C], data: Any, where: str = "", error: type[ConfigError] = ConfigError
) -> C:
    """Build the dataclass ``cls`` from a nested mapping; missing keys keep their defaults,
    unknown keys and wrong kinds raise ``error`` naming the dotted key."""
    if not isinstance(data, dict):
        raise error(where or "config", f"expected a mapping, got {show(data)}")
    known = {f.name: f for f in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(str(k) for k in set(data) - set(known))  # YAML keys may be numbers
    if unknown:
        raise error(where or "config", f"unknown key(s) {unknown}; known keys: {sorted(known)}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        default = _default_of(known[name])
        sub = f"{where}.{name}" if where else name
        if is_dataclass(default):
            kwargs[name] = config_from_dict(type(default), value, sub, error)
        else:
            kwargs[name] = _tupleize(value)
    try:
        return cls(**kwargs)
    except InvalidInputError:  # the dataclass's own check, already naming its field
        raise
    except (TypeError, ValueError) as exc:
        raise error(where or "config", str(exc)) from None


def read_yaml_mapping(
    path: str | Path,
    error: type[InvalidInputError] = ConfigError,
    what: str = "configuration",
) -> dict:
    """A YAML file's top-level mapping (an empty file is ``{}``), or ``error`` naming it.

    ``what`` names the kind of file in messages ("configuration", "calibration").
    """
    p = Path(path)
    if not p.is_file():
        raise error(p, f"{what} file does not exist")
    try:
        if p.stat().st_size > MAX_CONFIG_BYTES:
            raise error(p, f"larger than {MAX_CONFIG_BYTES} bytes: not a {what} file")
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise error(p, "not a text file (invalid UTF-8)") from None
    except yaml.YAMLError as exc:
        # PyYAML's message spans several lines; the CLI prints one.
        raise error(p, f"invalid YAML: {' '.join(str(exc).split())}") from None
    except RecursionError:
        raise error(p, "invalid YAML: nested too deeply") from None
    except OSError as exc:
        raise error(p, f"cannot read: {exc.strerror or exc}") from None
    if data is None:  # an empty file (or only comments): all defaults
        return {}
    if not isinstance(data, dict):
        raise error(p, f"expected a mapping of {what} keys, got {show(data)}")
    return data


def load_config_file(cls: type[C], path: str | Path, error: type[ConfigError] = ConfigError) -> C:
    """Read a YAML file into the dataclass ``cls``; errors name the file and dotted key."""
    data = read_yaml_mapping(path, error)
    try:
        return config_from_dict(cls, data, "", error)
    except ConfigError as exc:
        # "cfg.yaml: paths.preop_frames: ..."
        where = f"{path}: {exc.source}" if exc.source and exc.source != "config" else path
        raise error(where, exc.problem) from None


def to_plain(value: Any) -> Any:
    """A plain nested dict/list (JSON/YAML-ready) of a dataclass configuration."""
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_plain(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, tuple | list):
        return [to_plain(v) for v in value]
    return value


def replace_in(cfg: C, error: type[ConfigError] = ConfigError, **changes: Any) -> C:
    """Copy of ``cfg`` with dotted-key changes, e.g. ``replace_in(cfg, **{"camera.width":
    64})``; a value of ``None`` leaves the key as it is."""
    for key, value in changes.items():
        if value is None:
            continue
        cfg = _replace_path(cfg, key.split("."), value, key, error)
    return cfg


def _replace_path(obj: Any, parts: list[str], value: Any, key: str, error: type) -> Any:
    names = {f.name for f in fields(obj)}
    if parts[0] not in names:
        raise error(key, "unknown configuration key")
    if len(parts) == 1:
        return dataclasses.replace(obj, **{parts[0]: value})
    inner = getattr(obj, parts[0])
    if not is_dataclass(inner):
        raise error(key, "unknown configuration key")
    return dataclasses.replace(
        obj, **{parts[0]: _replace_path(inner, parts[1:], value, key, error)}
    )


# ------------------------------------------------------------------------------ argparse
def finite_float(text: str) -> float:
    """argparse ``type`` for a number option: NaN or inf would slip past every range check
    (``nan < 0`` is false) and switch gates off silently."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _scalar_parser(tp: Any) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(tp) if a is not type(None)]
        return _scalar_parser(options[0])
    return tp


def leaf_fields(cls: type, prefix: str = "") -> list[tuple[str, dataclasses.Field, type]]:
    """(dotted key, field, owning class) of every non-dataclass field, nested ones
    flattened (``change.threshold_mm``)."""
    out: list[tuple[str, dataclasses.Field, type]] = []
    for f in fields(cls):  # type: ignore[arg-type]
        default = _default_of(f)
        key = f"{prefix}{f.name}"
        if is_dataclass(default):
            out.extend(leaf_fields(type(default), key + "."))
        else:
            out.append((key, f, cls))
    return out


def add_config_arguments(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    exclude: tuple[str, ...] = (),
    aliases: dict[str, tuple[str, ...]] | None = None,
) -> None:
    """One ``--flag`` per leaf field of ``cls`` (nested dataclasses flattened; the flag is
    the field's own name, so names must be unique across the nesting), its help the
    field's docstring and its default shown; the parsed value stays ``None`` unless the
    flag is given, so a ``--config`` file and the defaults underneath are not overridden."""
    seen: dict[str, str] = {}
    for key, f, owner in leaf_fields(cls):
        if key in exclude or f.name in exclude:
            continue
        flag = _flag(f.name)
        if flag in seen:  # a programming error: two fields would share one flag
            raise TypeError(f"{cls.__name__}: {key} and {seen[flag]} both map to {flag}")
        seen[flag] = key
        tp = field_types(owner)[f.name]
        doc = field_docs(owner).get(f.name, "")
        default = _default_of(f)
        help_text = f"{doc} (default: {show(default) if not isinstance(default, str) else default})"
        base = _scalar_parser(tp)
        kwargs: dict[str, Any] = {"dest": key.replace(".", "__"), "default": None}
        if base is bool:
            kwargs["action"] = argparse.BooleanOptionalAction
        elif typing.get_origin(base) is Literal:
            kwargs["choices"] = typing.get_args(base)
        elif typing.get_origin(base) is tuple:
            args = typing.get_args(base)
            kwargs["nargs"] = "+" if len(args) == 2 and args[1] is Ellipsis else len(args)
            kwargs["type"] = finite_float if args[0] is float else args[0]
            kwargs["metavar"] = f.name.upper()
        elif base in (int, float, str):
            kwargs["type"] = finite_float if base is float else base
            kwargs["metavar"] = f.name.upper()
        else:
            raise TypeError(f"{key}: no flag for field type {tp!r}")
        extra = (aliases or {}).get(key, ())
        parser.add_argument(flag, *extra, help=help_text.replace("%", "%%"), **kwargs)


def config_from_args(
    cls: type[C],
    args: argparse.Namespace,
    base: C | None = None,
    error: type[ConfigError] = ConfigError,
) -> C:
    """``base`` (default: ``cls()``) with every flag the user gave applied on top."""
    cfg = cls() if base is None else base
    changes: dict[str, Any] = {}
    for key, _f, _owner in leaf_fields(cls):
        value = getattr(args, key.replace(".", "__"), None)
        if value is not None:
            changes[key] = tuple(value) if isinstance(value, list) else value
    try:
        return replace_in(cfg, error, **changes)
    except InvalidInputError:
        raise
    except (TypeError, ValueError) as exc:
        raise error("options", str(exc)) from None


MAX_SEEDS = 100_000
"""Most seeds one seed list may name (a typo like 0-999999999999 filled memory)."""


def seed_list(text: str) -> list[int]:
    """``"100-119"``, ``"1,4,9"`` or ``"7"`` (and mixtures like ``"1-3,8"``) -> sorted,
    distinct seeds >= 0; ValueError with the reason otherwise (callers name the option)."""
    seeds: set[int] = set()
    try:
        for part in str(text).split(","):
            part = part.strip()
            if not part:
                continue
            if "-" in part:
                a, b = (int(x) for x in part.split("-", 1))
                if b < a:
                    raise ValueError(f"range {part} is reversed")
                if b - a + 1 + len(seeds) > MAX_SEEDS:
                    raise OverflowError(
                        f"{part!r} names {b - a + 1} seeds, over the limit of {MAX_SEEDS}"
                    )
                seeds.update(range(a, b + 1))
            else:
                seeds.add(int(part))
    except OverflowError as exc:
        raise ValueError(str(exc)) from None
    except ValueError as exc:
        raise ValueError(f"expected e.g. '100-119' or '1,4,9', got {text!r} ({exc})") from None
    if not seeds or min(seeds) < 0:
        raise ValueError(f"expected one or more seeds >= 0, got {text!r}")
    return sorted(seeds)
