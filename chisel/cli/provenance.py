"""What ``chisel depth`` records beside what it writes: the command that reproduces a run,
the environment it ran in, the parent a fine-tuning started from, and the one-line JSON
summary on stdout. One home for the monocular and the change-aware commands, so their
checkpoint sidecars and predictions say the same things the same way."""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import shlex
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Protocol

import torch


def sha256_file(path: Path) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB chunks (checkpoints are tens of MB)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def canonical_command(args: argparse.Namespace, names: list[str]) -> str:
    """The command line that reproduces this run, every option in ``names`` spelled out."""
    words = ["chisel", "depth", args.depth_command]
    for name in names:
        value = getattr(args, name)
        flag = "--" + name.replace("_", "-")
        if isinstance(value, bool):
            if value:
                words.append(flag)
        elif value is None:
            continue
        elif isinstance(value, list):
            words += [flag, *(str(v) for v in value)]
        elif isinstance(value, tuple):
            if name == "size":
                words += [flag, f"{value[0]}x{value[1]}"]
            else:
                words += [flag, ",".join(str(v) for v in value)]
        else:
            words += [flag, str(value)]
    return shlex.join(words)


def environment() -> dict[str, Any]:
    """Versions and thread count: same data, config and threads give the same weights."""
    return {
        "torch": torch.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "threads": torch.get_num_threads(),
    }


class _Config(Protocol):
    def to_dict(self) -> dict[str, Any]: ...


class _Run(Protocol):
    @property
    def seconds(self) -> float: ...
    @property
    def history(self) -> list[dict[str, float]]: ...


def finetune_info(
    command: str,
    parent: Path,
    parent_info: Mapping[str, Any],
    sequences: list[str],
    num_train_frames: int,
    cfg: _Config,
    result: _Run,
    target: list[str] | None = None,
) -> dict[str, Any]:
    """The sidecar of a fine-tuned checkpoint: its parent (path, hash, the parent's own
    record less its history) and the fine-tuning run (config, wall time, history).
    ``target``: what the change-aware network was fine-tuned towards (None for the
    monocular network, which has one target)."""
    info: dict[str, Any] = {"kind": "finetune", "command": command}
    if target is not None:
        info["target"] = target
    return info | {
        "parent_checkpoint": str(parent),
        "parent_sha256": sha256_file(parent),
        "parent_info": {k: v for k, v in parent_info.items() if k != "history"},
        "finetune_sequences": sequences,
        "num_train_frames": num_train_frames,
        "train_config": cfg.to_dict(),
        "train_seconds": round(result.seconds, 1),
        "history": result.history,
        "environment": environment(),
    }


def write_summary(doc: Mapping[str, Any]) -> None:
    """The command's result as one JSON line on stdout (for scripts and the logs)."""
    sys.stdout.write(json.dumps(doc) + "\n")
