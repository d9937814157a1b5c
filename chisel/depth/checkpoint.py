"""Depth-network checkpoints: a state_dict plus a JSON-able config, loadable without pickle.

File layout (``torch.save`` of a plain dict, read with ``torch.load(weights_only=True)``)::

    {"format": "endoscopic-chisel/depth-checkpoint", "version": 1,
     "config": DepthNetConfig.to_dict(), "state_dict": {name: tensor},
     "info": {...}}   # JSON-able: training command, seeds, metrics, parent checkpoint

Beside ``X.pt`` a human-readable ``X.json`` carries the same config and info.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from chisel.core.atomic import atomic_paths
from chisel.core.errors import FormatVersionError, InvalidInputError
from chisel.depth.network import DepthNet, DepthNetConfig

CHECKPOINT_FORMAT = "endoscopic-chisel/depth-checkpoint"
CHECKPOINT_VERSION = 1
KIND_MONOCULAR = "monocular"
KIND_CHANGE_AWARE = "change-aware"
"""Checkpoint kinds (``payload["kind"]``); a file without a kind is monocular (older files)."""


class CheckpointError(InvalidInputError):
    """A depth checkpoint is unreadable or does not match the network architecture."""


def _json_able(info: dict[str, Any], source: str) -> dict[str, Any]:
    try:
        return json.loads(json.dumps(info))
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(source, f"checkpoint info must be JSON-able: {exc}") from None


def nonfinite_tensors(tensors: dict[str, torch.Tensor]) -> list[str]:
    """Names of the floating-point tensors in ``tensors`` holding NaN or inf."""
    return [
        k
        for k, v in tensors.items()
        if torch.is_tensor(v) and v.is_floating_point() and not bool(torch.isfinite(v).all())
    ]


def checkpoint_kind_error(
    path: str | Path, payload: dict[str, Any], expected: str
) -> CheckpointError | None:
    """The error for a checkpoint of another kind than ``expected`` (naming both), or None."""
    kind = payload.get("kind", KIND_MONOCULAR)
    if kind == expected:
        return None
    return CheckpointError(
        path,
        f"this is a {kind!r} depth checkpoint, but a {expected!r} checkpoint is expected here "
        f"(monocular: chisel depth train; change-aware: chisel depth train --kind change-aware)",
    )


def sidecar_path(path: str | Path) -> Path:
    """The ``.json`` that :func:`save_checkpoint` writes beside the checkpoint ``path``."""
    return Path(path).with_suffix(".json")


def save_checkpoint(path: str | Path, net: DepthNet, info: dict[str, Any] | None = None) -> Path:
    """Write ``net`` to ``path`` (atomically) and a ``.json`` sidecar; returns ``path``.

    info : JSON-able dict (training command, seeds, metrics, ...).
    """
    path = Path(path)
    if path.suffix != ".pt":
        raise InvalidInputError(path, f"checkpoint file must end in .pt, got {path.suffix!r}")
    info = _json_able(dict(info or {}), str(path))
    bad = nonfinite_tensors(dict(net.state_dict()))
    if bad:
        # A network with NaN weights predicts no valid pixel; saving it would only move
        # the failure to whoever loads it.
        raise CheckpointError(
            path,
            f"refusing to save a network with NaN/inf in {len(bad)} tensor(s), e.g. "
            f"{bad[:3]} (training diverged?)",
        )
    payload = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "kind": KIND_MONOCULAR,
        "config": net.config.to_dict(),
        "state_dict": {k: v.detach().cpu().clone() for k, v in net.state_dict().items()},
        "info": info,
    }
    sidecar = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "weights": path.name,
        "num_parameters": int(sum(p.numel() for p in net.parameters())),
        "config": net.config.to_dict(),
        "info": info,
    }
    write_checkpoint_files(path, payload, sidecar)
    return path


def write_checkpoint_files(path: Path, payload: dict[str, Any], sidecar: dict[str, Any]) -> None:
    """The weights at ``path`` and their ``.json`` sidecar, moved into place together: both
    new or, after a failure (a full disk while the sidecar is written), both as they were."""
    with atomic_paths(path, sidecar_path(path)) as (tmp, tmp_json):
        torch.save(payload, tmp)
        tmp_json.write_text(json.dumps(sidecar, indent=2) + "\n")


def _describe_mismatch(
    expected: dict[str, torch.Tensor], got: dict[str, torch.Tensor]
) -> list[str]:
    problems = []
    missing = sorted(set(expected) - set(got))
    unexpected = sorted(set(got) - set(expected))
    if missing:
        problems.append(f"{len(missing)} missing tensor(s), e.g. {missing[:3]}")
    if unexpected:
        problems.append(f"{len(unexpected)} unexpected tensor(s), e.g. {unexpected[:3]}")
    for k in sorted(set(expected) & set(got)):
        if tuple(expected[k].shape) != tuple(got[k].shape):
            problems.append(
                f"{k}: expected shape {tuple(expected[k].shape)}, got {tuple(got[k].shape)}"
            )
    return problems


def read_checkpoint(path: str | Path, kind: str) -> dict[str, Any]:
    """The payload of a depth checkpoint of ``kind``, read with ``weights_only=True``:
    the file exists, is a checkpoint of this format and version, and of the kind asked for
    (the other kind is refused naming both). Shared by both networks' loaders."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(path, "checkpoint file does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a foreign/corrupt file
        raise CheckpointError(
            path,
            f"cannot read as a depth checkpoint with weights_only=True ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0] if str(exc) else ''}); an exported TorchScript model "
            f"is loaded with chisel.depth.load_depth_source instead",
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        fmt = payload.get("format") if isinstance(payload, dict) else type(payload).__name__
        raise CheckpointError(path, f"format is {fmt!r}, expected {CHECKPOINT_FORMAT!r}")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise FormatVersionError(
            path,
            f"depth checkpoint version {payload.get('version')!r}; this reader reads "
            f"version {CHECKPOINT_VERSION}",
        )
    kind_error = checkpoint_kind_error(path, payload, kind)
    if kind_error is not None:
        raise kind_error
    return payload


def fill_weights(
    path: str | Path, net: torch.nn.Module, payload: dict[str, Any], architecture: object
) -> None:
    """Load the payload's weights into ``net`` (then eval mode), refusing weights that do
    not fit the ``architecture`` (shown in the message) or hold NaN/inf."""
    state = payload.get("state_dict")
    if not isinstance(state, dict):
        raise CheckpointError(path, "no state_dict in checkpoint")
    for key, value in state.items():
        if not isinstance(key, str):
            raise CheckpointError(
                path, f"state_dict key {key!r} is {type(key).__name__}, expected a tensor name"
            )
        if not torch.is_tensor(value):
            raise CheckpointError(
                path, f"state_dict[{key!r}] is {type(value).__name__}, expected a tensor"
            )
    problems = _describe_mismatch(net.state_dict(), state)
    if problems:
        raise CheckpointError(
            path,
            f"weights do not match the architecture {architecture}: " + "; ".join(problems),
        )
    bad = nonfinite_tensors(state)
    if bad:
        raise CheckpointError(
            path,
            f"{len(bad)} weight tensor(s) hold NaN/inf, e.g. {bad[:3]}: the network would "
            "predict no valid depth (a diverged training run?); retrain with a lower --lr "
            "or use an earlier checkpoint",
        )
    net.load_state_dict(state, strict=True)
    net.eval()


def checkpoint_info(path: str | Path, payload: dict[str, Any]) -> dict[str, Any]:
    """The payload's ``info``: a JSON-able dict (``{}`` in a file without one). Shared by
    both networks' loaders."""
    info = payload.get("info", {})
    if not isinstance(info, dict):
        raise CheckpointError(
            path, f"info must be a dict (JSON object), got {type(info).__name__}: {info!r:.60}"
        )
    return _json_able(info, str(path))


def load_checkpoint(
    path: str | Path, config: DepthNetConfig | None = None
) -> tuple[DepthNet, dict[str, Any]]:
    """Load a checkpoint into a fresh :class:`DepthNet` (eval mode, CPU).

    config : build this architecture instead of the stored one (e.g. to check that a
    checkpoint fits an expected network); a mismatch raises :class:`CheckpointError`.
    Returns ``(net, info)``.
    """
    payload = read_checkpoint(path, KIND_MONOCULAR)
    stored = DepthNetConfig.from_dict(payload.get("config", {}), f"{path} config")
    net = DepthNet(config or stored)
    fill_weights(path, net, payload, (config or stored).to_dict())
    return net, checkpoint_info(path, payload)
