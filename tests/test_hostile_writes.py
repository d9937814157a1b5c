"""Outputs that belong together are replaced together: a failure while the last of them is
written leaves every one as it was (a checkpoint and its sidecar; a table's JSON, CSV and
Markdown). Each test fails on the code before the fix, which wrote them one at a time."""

from __future__ import annotations

import errno
import json
import sys
from pathlib import Path

import pytest
import torch

import chisel.eval.tables as tables_mod
from chisel.depth.change_aware import ChangeNet, ChangeNetConfig, save_change_checkpoint
from chisel.depth.checkpoint import save_checkpoint
from chisel.depth.network import DepthNet, DepthNetConfig
from chisel.eval.tables import (
    METRIC_KEYS,
    aggregate_seeds,
    assemble_table,
    write_seed_table,
    write_table,
)
from sim.config import SimConfig, replace_in
from sim.dataset import build_dataset
from sim.errors import SimError


def _disk_full(*_args: object, **_kwargs: object) -> str:
    raise OSError(errno.ENOSPC, "No space left on device")


def _snapshot(*paths: Path) -> list[bytes]:
    return [p.read_bytes() for p in paths]


def _perturbed(net: torch.nn.Module) -> torch.nn.Module:
    with torch.no_grad():
        for p in net.parameters():
            p.add_(1.0)
    return net


@pytest.mark.parametrize("kind", ["monocular", "change-aware"])
def test_a_failed_sidecar_leaves_the_checkpoint_as_it_was(
    tmp_path: Path, kind: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    def save(info: dict) -> Path:
        if kind == "monocular":
            net = DepthNet(DepthNetConfig(widths=(4, 8), blocks=(0, 0)))
            return save_checkpoint(tmp_path / "net.pt", _perturbed(net) if info else net, info)
        change = ChangeNet(ChangeNetConfig(widths=(8, 12), input_scale=1.0))
        return save_change_checkpoint(tmp_path / "net.pt", _perturbed(change), info)

    path = save({})
    before = _snapshot(path, path.with_suffix(".json"))
    # The sidecar's text is made after the weights are staged: a full disk there (the
    # info's own JSON check, before anything is written, still runs).
    dumps = json.dumps

    def sidecar_fails(obj: object, *args: object, **kwargs: object) -> str:
        if isinstance(obj, dict) and "weights" in obj:
            _disk_full()
        return dumps(obj, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(json, "dumps", sidecar_fails)
    with pytest.raises(OSError, match="No space left"):
        save({"run": "second"})
    assert _snapshot(path, path.with_suffix(".json")) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["net.json", "net.pt"]


def _metrics(mean_mm: float) -> dict:
    cell: dict[str, float | None] = {k: mean_mm for k in METRIC_KEYS}
    cell.update(n_points=100, n_gt_in_box=110, mask_precision=None, mask_recall=None)
    steps = [{"step": s, "label": "", "methods": {"updated": dict(cell)}} for s in (0, 1)]
    return assemble_table(steps, "writes")


def test_a_failed_markdown_leaves_the_whole_table_as_it_was(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    paths = write_table(tmp_path, _metrics(0.1))
    seed_paths = write_seed_table(tmp_path, aggregate_seeds([_metrics(0.1)], ["seed 0"]))
    before = _snapshot(*paths.values(), *seed_paths.values())
    monkeypatch.setattr(tables_mod, "metrics_to_markdown", _disk_full)
    monkeypatch.setattr(tables_mod, "seeds_to_markdown", _disk_full)
    with pytest.raises(OSError, match="No space left"):
        write_table(tmp_path, _metrics(0.2))
    with pytest.raises(OSError, match="No space left"):
        write_seed_table(tmp_path, aggregate_seeds([_metrics(0.2)], ["seed 0"]))
    assert _snapshot(*paths.values(), *seed_paths.values()) == before
    assert len(list(tmp_path.iterdir())) == 6  # no temporary file left behind


def test_a_failed_rerun_of_a_dataset_leaves_no_index_of_renders_it_replaced(
    tmp_path: Path, tiny_sim_config: SimConfig
) -> None:
    # The generator contract (--seed S --bites N --out DIR), the toy phantom, refusing seed 2.
    gen_py = tmp_path / "gen.py"
    gen_py.write_text(
        "import runpy, sys\n"
        "args = sys.argv[1:]\n"
        "if args[args.index('--seed') + 1] == '2' and 'FAIL' in sys.argv[0]:\n"
        "    sys.exit('refused')\n"
        "sys.argv = ['sim.synthetic', *args]\n"
        "runpy.run_module('sim.synthetic', run_name='__main__')\n"
    )
    failing = tmp_path / "FAIL_gen.py"
    failing.write_text(gen_py.read_text())
    out = tmp_path / "ds"
    cfg = tiny_sim_config
    build_dataset(out, [1, 2], cfg, bites=1, phantom_cmd=f"{sys.executable} {gen_py}")
    assert (out / "dataset.json").is_file() and (out / "dataset_card.json").is_file()
    seed_2 = _snapshot(out / "seed_2" / "render.json")
    # Another master seed: seed 1 is rendered again, then seed 2's phantom fails.
    with pytest.raises(SimError, match="seed 2"):
        build_dataset(
            out, [1, 2], replace_in(cfg, seed=7), bites=1, phantom_cmd=f"{sys.executable} {failing}"
        )
    assert not (out / "dataset.json").exists() and not (out / "dataset_card.json").exists()
    assert _snapshot(out / "seed_2" / "render.json") == seed_2
