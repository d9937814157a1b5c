"""The dataset card names what reproduces the dataset: running its command again gives the
same dataset (bytes), and it records seeds, ranges, drawn values, counts and the split."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import yaml

from chisel.io.sequence import Sequence
from sim.cli import main
from sim.dataset import split_by_seed


def test_dataset_card_reproduces_the_dataset(tmp_path: Path) -> None:
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                "camera": {"width": 32, "height": 24},
                "imaging": {"spp": 1},
                "appearance": {"texture_voxel_mm": 1.0},
                "paths": {"preop_frames": 2, "intraop_frames": 2},
                "randomization": {"smoke_density_per_mm": [0.01, 0.05]},
            }
        )
    )
    args = ["dataset", "--seeds", "3-5", "--bites", "1", "--config", str(cfg), "--quiet"]
    gen = ["--phantom-cmd", f"{sys.executable} -m sim.synthetic"]
    assert main([*args, "--out", str(tmp_path / "a"), *gen]) == 0
    card = json.loads((tmp_path / "a/dataset_card.json").read_text())
    ds = json.loads((tmp_path / "a/dataset.json").read_text())
    assert card["format"] == "endoscopic-chisel/dataset-card" and card["version"] == 1
    assert card["dataset_format"] == {"format": ds["format"], "version": ds["version"]}
    assert card["command"][:3] == ["python", "-m", "sim"] and "--seeds" in card["command"]
    assert card["phantom_seeds"] == [3, 4, 5] and card["master_seed"] == 0
    assert card["counts"]["frames"] == ds["num_frames"] and card["counts"]["phantoms"] == 3
    assert card["split"] == {"train": [3], "val": [4], "test": [5]}
    assert card["ranges"]["smoke_density_per_mm"] == [0.01, 0.05]
    for seed in (3, 4, 5):
        render = json.loads((tmp_path / f"a/seed_{seed}/render.json").read_text())
        drawn = card["drawn"][str(seed)]
        assert drawn["smoke.density_per_mm"] == render["config"]["smoke"]["density_per_mm"]
        assert 0.01 <= drawn["smoke.density_per_mm"] <= 0.05
        assert drawn["appearance.roughness"] == render["config"]["appearance"]["roughness"]
    # The recorded command, run again into another folder, gives the same dataset.
    command = card["command"][3:]
    out = command.index("--out")
    command[out + 1] = str(tmp_path / "b")
    assert main(command) == 0
    ds_b = json.loads((tmp_path / "b/dataset.json").read_text())
    assert ds_b["sequences"] == ds["sequences"] and ds_b["config"] == ds["config"]
    a, b = Sequence(tmp_path / "a/seed_4/step_01"), Sequence(tmp_path / "b/seed_4/step_01")
    assert np.array_equal(a.rgb(1), b.rgb(1))


def test_split_is_by_phantom_seed_and_disjoint() -> None:
    seeds = list(range(100, 120))
    s = split_by_seed(seeds)
    assert len(s["test"]) == 2 and len(s["val"]) == 2 and len(s["train"]) == 16
    assert sorted(s["train"] + s["val"] + s["test"]) == seeds
    assert split_by_seed([7]) == {"train": [7], "val": [], "test": []}
