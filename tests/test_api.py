"""The public API of ``chisel``: every exported name resolves, the docstring's example
runs as written, and ``import chisel`` stays cheap for the command line."""

from __future__ import annotations

import doctest
import subprocess
import sys

import chisel


def test_every_exported_name_resolves() -> None:
    for name in chisel.__all__:
        assert getattr(chisel, name) is not None, name


def test_docstring_example_runs() -> None:
    result = doctest.testmod(chisel, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 10
    assert result.failed == 0


def test_import_is_lazy() -> None:
    code = "import sys, chisel; print(sorted(m for m in ('open3d', 'torch', 'numba', 'mitsuba') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_unknown_name_is_an_attribute_error() -> None:
    try:
        chisel.no_such_thing  # noqa: B018
    except AttributeError as exc:
        assert "no_such_thing" in str(exc)
    else:
        raise AssertionError("chisel.no_such_thing resolved")


def test_all_lists_exactly_the_exports() -> None:
    assert sorted(chisel.__all__) == sorted(chisel._EXPORTS)
