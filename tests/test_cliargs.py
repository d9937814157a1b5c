"""chisel commands refuse outputs that would overwrite their inputs or each other.

The check runs before anything is read, so the inputs here only need to exist.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from chisel.cli import main


@pytest.fixture
def files(tmp_path: Path) -> dict[str, Path]:
    seq = tmp_path / "r" / "step_01"
    seq.mkdir(parents=True)
    (seq / "sequence.json").write_text("{}")
    (seq / "poses.txt").write_text("")
    model = tmp_path / "model.npz"
    model.write_bytes(b"not read")
    surface = tmp_path / "surf.ply"
    surface.write_bytes(b"not read")
    return {"seq": seq, "model": model, "surface": surface, "root": tmp_path}


def refused(argv: list[str], capsys: pytest.CaptureFixture[str], *words: str) -> None:
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1, err
    for w in words:
        assert w in err, err


def test_update_refuses_overwriting_its_model_and_sequence(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    model, seq = str(files["model"]), str(files["seq"])
    base = ["update", "--model", model, "--sequence", seq]
    refused([*base, "--out", model], capsys, "--out", "would overwrite the input --model")
    refused(
        [*base, "--out", str(files["root"] / "u.npz"), "--report", model],
        capsys,
        "--report",
        "would overwrite the input --model",
    )
    refused(
        [*base, "--out", str(files["root"] / "u.npz"), "--report", f"{seq}/poses.txt"],
        capsys,
        "--report",
        "lies inside the input folder --sequence",
    )
    refused(
        [*base, "--out", str(files["root"] / "u.npz"), "--masks", str(files["root"] / "u.npz")],
        capsys,
        "one output would overwrite the other",
    )
    # The path inside a "sequence:DIR" depth source is an input too.
    other = files["root"] / "pred"
    other.mkdir()
    refused(
        [*base, "--depth-source", f"sequence:{other}", "--out", str(other / "u.npz")],
        capsys,
        "lies inside the input folder --depth-source",
    )
    assert files["model"].read_bytes() == b"not read"


def test_folder_outputs_may_not_hold_their_input(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    seq, surface = str(files["seq"]), str(files["surface"])
    parent = str(files["seq"].parent)
    refused(
        ["render-depth", "--mesh", surface, "--sequence", seq, "--out", parent],
        capsys,
        "would overwrite the input --sequence",
    )
    refused(
        ["render-depth", "--mesh", surface, "--sequence", seq, "--out", seq],
        capsys,
        "would overwrite the input --sequence",
    )
    refused(
        ["depth", "predict", "--sequence", seq, "--out", parent],
        capsys,
        "would overwrite the input --sequence",
    )
    assert (files["seq"] / "sequence.json").read_text() == "{}"


def test_file_outputs_may_not_be_an_input(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    surface, seq = str(files["surface"]), str(files["seq"])
    refused(
        ["build", "--surface", surface, "--sequence", seq, "--out", surface],
        capsys,
        "would overwrite the input --surface",
    )
    refused(
        ["depth", "predict", "--sequence", seq, "--out", f"{seq}/../step_01"],
        capsys,
        "would overwrite the input --sequence",
    )
    assert files["surface"].read_bytes() == b"not read"


def test_sidecar_outputs_are_checked_too(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    # update writes OUT.json when no --report is given; a checkpoint writes a .json beside it.
    model, seq, root = str(files["model"]), str(files["seq"]), files["root"]
    metrics = root / "u.json"
    metrics.write_text("{}")
    base = ["update", "--model", model, "--sequence", seq, "--out", str(root / "u.npz")]
    refused([*base, "--depth-source", f"sequence:{metrics}"], capsys, "--out sidecar", str(metrics))
    refused(
        [*base, "--masks", str(root / "u.json")], capsys, "one output would overwrite the other"
    )
    # With --report there is no default report: the check passes, reading the model fails.
    refused(
        [*base, "--report", str(root / "r.json"), "--masks", str(root / "u.json")],
        capsys,
        "cannot read model",
    )
    data = root / "data.json"
    data.write_text("{}")
    refused(
        ["depth", "train", "--data", str(data), "--out", str(root / "data.pt")],
        capsys,
        "--out sidecar",
        "would overwrite the input --data",
    )
    refused(
        ["depth", "finetune", "--checkpoint", str(metrics), "--sequence", seq]
        + ["--out", str(root / "u.pt")],
        capsys,
        "--out sidecar",
        "would overwrite the input --checkpoint",
    )
    assert metrics.read_text() == data.read_text() == "{}"


def test_number_options_refuse_nan_and_inf(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    base = ["update", "--model", str(files["model"]), "--sequence", str(files["seq"])]
    base += ["--out", str(files["root"] / "u.npz")]
    for option, value in [("--tracking-accuracy-mm", "nan"), ("--depth-noise-mm", "inf")]:
        with pytest.raises(SystemExit) as exc:
            main([*base, option, value])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert option in err and "expected a finite number" in err, err


def test_evaluate_refuses_a_negative_seed(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    refused(
        ["evaluate", "--seed", "-1", "--out", str(files["root"] / "m.json")],
        capsys,
        "--seed: must be >= 0",
    )


def test_update_reads_its_parameters_from_a_config_file(
    files: dict[str, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    """``--config`` holds UpdateConfig's fields; a wrong key or kind is refused naming the
    file and the dotted key, before anything else is read or written."""
    base = ["update", "--model", str(files["model"]), "--sequence", str(files["seq"])]
    base += ["--out", str(files["root"] / "u.npz")]
    cfg = files["root"] / "update.yaml"
    cfg.write_text("change:\n  threshold: 2.0\n")
    refused(
        [*base, "--config", str(cfg)], capsys, "update.yaml: change: unknown key(s) ['threshold']"
    )
    cfg.write_text("registration:\n  min_fitness: high\n")
    refused([*base, "--config", str(cfg)], capsys, "registration.min_fitness: expected a number")
    cfg.write_text("carve: sideways\n")
    refused([*base, "--config", str(cfg)], capsys, "carve: expected one of deletion, paper")
    assert not (files["root"] / "u.npz").exists()


def test_update_flags_are_generated_from_the_config_fields() -> None:
    import dataclasses

    from chisel.cli import build_parser
    from chisel.core.config import config_from_args, leaf_fields
    from chisel.update_config import UpdateConfig

    parser = build_parser(["update"])
    args = parser.parse_args(
        ["update", "--model", "m", "--sequence", "s", "--out", "o.npz", "--min-views", "2",
         "--no-registration", "--icp-max-dist-mm", "2", "1", "--carve", "paper"]
    )  # fmt: skip
    cfg = config_from_args(UpdateConfig, args)
    assert (cfg.change.min_views, cfg.register, cfg.carve) == (2, False, "paper")
    assert cfg.registration.icp_max_dist_mm == (2.0, 1.0)
    # Every leaf field has its flag, and nothing else changed.
    assert (
        dataclasses.replace(
            cfg,
            change=UpdateConfig().change.__class__(
                **{**dataclasses.asdict(cfg.change), "min_views": 5}
            ),
            registration=UpdateConfig().registration,
            register=True,
            carve="deletion",
        )
        == UpdateConfig()
    )
    text = parser._subparsers._group_actions[0].choices["update"].format_help()  # noqa: SLF001
    for key, f, _ in leaf_fields(UpdateConfig):
        assert "--" + f.name.replace("_", "-") in text, key
