"""An anatomy the endoscope cannot reach is drawn again: every seed gets a phantom.

Seed 25's first parameter draw has no airway that keeps the endoscope 3 mm from the tissue
on its way to the uncinate (found by scanning seeds 0-129 for phantoms that could not be
built; 25, 56, 83 and 126 were the four). The generator takes the seed's next draw; an
explicit plan, made for one anatomy, is not moved to another.
"""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import trimesh

from phantoms.anatomy import arrays_from_manifold, build_anatomy
from phantoms.ct import SurfaceDistance
from phantoms.errors import AnatomyError
from phantoms.generate import build_phantom
from phantoms.params import PARAM_RANGES, PhantomConfig, sample_params
from phantoms.path import airway_path

# the package exports a function of the module's name: the module itself, to patch it
generate = importlib.import_module("phantoms.generate")


def test_draw_zero_is_the_seeds_first_and_later_draws_differ() -> None:
    assert sample_params(7) == sample_params(7, draw=0)
    second = sample_params(7, draw=1)
    assert second != sample_params(7) and second == sample_params(7, draw=1)
    for name, (lo, hi, _) in PARAM_RANGES.items():
        assert lo <= second[name] <= hi, name
    assert sample_params(7, {"airway_length_mm": 70.0}, draw=1)["airway_length_mm"] == 70.0
    with pytest.raises(ValueError, match="draw"):
        sample_params(7, draw=-1)


def test_a_later_draw_is_a_new_anatomy_and_plan_and_draw_zero_the_seeds_own() -> None:
    assert generate.draw_seed(7, 0) == 7
    later = [generate.draw_seed(7, k) for k in range(1, 6)]
    assert len(set(later)) == 5 and 7 not in later
    assert all(0 <= s < 2**31 for s in later)
    assert later == [generate.draw_seed(7, k) for k in range(1, 6)]
    assert generate.draw_seed(8, 1) != generate.draw_seed(7, 1)


def test_a_seed_without_an_airway_takes_its_next_draw() -> None:
    config = PhantomConfig(seed=25, ct=False)
    first = build_anatomy(sample_params(25), 25, config.mesh_edge_mm)
    target = generate._cut_plan(first, config, None, "plan")[0]
    with pytest.raises(AnatomyError, match="no path from the nostril"):
        airway_path(
            SurfaceDistance(*arrays_from_manifold(first.tissue)),
            np.asarray(first.nostril_mm),
            np.asarray(first.airway_min_mm),
            np.asarray(first.airway_max_mm),
            target,
        )
    ph = build_phantom(config)
    # the first later draw with an airway and a specimen-sized uncinectomy
    # (tests/test_phantoms_regime.py)
    assert ph.anatomy_draw >= 1
    assert {k: ph.params[k] for k in PARAM_RANGES} == sample_params(25, draw=ph.anatomy_draw)
    # the path keeps the endoscope's clearance from the tissue, by trimesh's own distance
    preop = trimesh.Trimesh(ph.steps[0].vertices_mm, ph.steps[0].faces, process=False)
    dense = np.concatenate(
        [
            np.linspace(a, b, 5, endpoint=False)
            for a, b in zip(ph.airway_path_mm[:-1], ph.airway_path_mm[1:], strict=True)
        ]
    )
    _, distance, _ = trimesh.proximity.closest_point(preop, dense)
    assert distance.min() >= 3.0 - 1e-6
    assert ph.steps[-1].removed_volume_mm3 > 0


def _no_airway(*_args, **_kwargs):
    raise AnatomyError("airway_path", "no path from the nostril to a view of the uncinate")


def test_every_draw_without_an_airway_is_an_error_naming_the_seed(monkeypatch) -> None:
    monkeypatch.setattr(generate, "airway_path", _no_airway)
    monkeypatch.setattr(generate, "MAX_ANATOMY_DRAWS", 2)
    with pytest.raises(AnatomyError, match=r"seed 3: none of 2 anatomy draws"):
        build_phantom(PhantomConfig(seed=3, ct=False))


def test_an_explicit_plan_keeps_its_anatomy(monkeypatch) -> None:
    planned = build_phantom(PhantomConfig(seed=0, ct=False, procedure="bites", n_bites=1))
    monkeypatch.setattr(generate, "airway_path", _no_airway)
    with pytest.raises(AnatomyError) as info:
        build_phantom(PhantomConfig(seed=0, ct=False, procedure="bites"), list(planned.bites))
    assert "draws" not in info.value.problem
