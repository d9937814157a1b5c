"""chisel.core.config: one dataclass, checked the same way from YAML, flags and code."""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from typing import Literal

import pytest

from chisel.core.config import (
    add_config_arguments,
    check_fields,
    config_from_args,
    config_from_dict,
    field_docs,
    load_config_file,
    replace_in,
    to_plain,
)
from chisel.core.errors import ConfigError


@dataclass(frozen=True)
class Inner:
    threshold_mm: float = 1.0
    """Change threshold, mm."""
    mode: Literal["fast", "exact"] = "fast"
    """How hard to try."""

    def __post_init__(self) -> None:
        check_fields(self, "inner")


@dataclass(frozen=True)
class Outer:
    inner: Inner = field(default_factory=Inner)
    """The inner part."""
    views: int = 5
    """Other frames that must agree."""
    register: bool = True
    """Register the estimate to the render."""
    box_mm: tuple[float, float] = (0.0, 1.0)
    """A range, mm."""
    note: str | None = None
    """Free text."""

    def __post_init__(self) -> None:
        check_fields(self)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    add_config_arguments(p, Outer)
    return p


def test_field_docs_are_the_strings_after_each_field() -> None:
    assert field_docs(Inner) == {
        "threshold_mm": "Change threshold, mm.",
        "mode": "How hard to try.",
    }
    assert field_docs(Outer)["views"] == "Other frames that must agree."


def test_flags_come_from_the_fields_with_their_docstrings_as_help() -> None:
    text = _parser().format_help()
    for flag in ("--threshold-mm", "--mode", "--views", "--register", "--no-register", "--box-mm"):
        assert flag in text
    assert "Other frames that must agree. (default: 5)" in " ".join(text.split())


def test_flags_override_only_what_is_given() -> None:
    args = _parser().parse_args(["--threshold-mm", "2.5", "--no-register", "--box-mm", "1", "3"])
    cfg = config_from_args(Outer, args)
    assert cfg == Outer(inner=Inner(threshold_mm=2.5), register=False, box_mm=(1.0, 3.0))
    base = Outer(views=9)
    assert config_from_args(Outer, _parser().parse_args([]), base) is base


def test_yaml_file_round_trip_and_flags_on_top(tmp_path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("inner:\n  mode: exact\nviews: 7\n")
    cfg = load_config_file(Outer, path)
    assert cfg == Outer(inner=Inner(mode="exact"), views=7)
    assert to_plain(cfg)["inner"] == {"threshold_mm": 1.0, "mode": "exact"}
    on_top = config_from_args(Outer, _parser().parse_args(["--views", "3"]), cfg)
    assert (on_top.views, on_top.inner.mode) == (3, "exact")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("inner:\n  threshold: 2\n", r"c\.yaml: inner: unknown key\(s\) \['threshold'\]"),
        ("views: 2.5\n", r"c\.yaml: views: expected an integer, got 2\.5"),
        ("register: 'no'\n", r"c\.yaml: register: expected true or false"),
        ("inner:\n  mode: slow\n", r"c\.yaml: inner\.mode: expected one of fast, exact"),
        ("box_mm: [1, 2, 3]\n", r"c\.yaml: box_mm: expected a list of 2 numbers, got 3"),
        ("- 1\n- 2\n", r"c\.yaml: expected a mapping"),
        ("views: [\n", r"c\.yaml: invalid YAML"),
        ("inner: .nan\n", r"c\.yaml: inner: expected a mapping"),
    ],
)
def test_bad_files_name_the_file_and_the_key(tmp_path, text: str, message: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_config_file(Outer, path)


def test_a_missing_file_and_a_nan_are_refused(tmp_path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        load_config_file(Outer, tmp_path / "none.yaml")
    with pytest.raises(ConfigError, match="inner.threshold_mm: expected a finite number"):
        config_from_dict(Outer, {"inner": {"threshold_mm": float("nan")}})


def test_replace_in_follows_dotted_keys() -> None:
    cfg = replace_in(Outer(), **{"inner.threshold_mm": 3.0, "views": 1})
    assert (cfg.inner.threshold_mm, cfg.views) == (3.0, 1)
    with pytest.raises(ConfigError, match="inner.nope: unknown configuration key"):
        replace_in(Outer(), **{"inner.nope": 1})
