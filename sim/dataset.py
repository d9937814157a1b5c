"""A training set for the depth network: many phantom seeds, randomised appearance.

For every seed: generate a phantom by running the phantom generator's CLI in a
subprocess (``python -m phantoms generate --seed S --bites N --out DIR/phantoms/seed_S``;
``sim`` never imports ``phantoms``), draw an appearance from the config's randomisation
ranges, and render its preoperative sweep and intraoperative sequences (RGB + depth,
direct lighting). Layout::

    DIR/dataset.json            format, version, sequences [{path, phantom_seed, kind, step,
                                num_frames}], seeds, config
    DIR/dataset_card.json       what reproduces it: command, seeds, ranges and the values drawn
                                per seed, counts, the split by phantom seed, format version
    DIR/phantoms/seed_S/        the generated phantom
    DIR/seed_S/                 a render folder (render.json, preop/, step_01/, ...)

Each seed's render appears atomically; ``dataset.json`` is written last. With ``resume``
seeds whose render folder is complete are kept.
"""

from __future__ import annotations

import dataclasses
import gc
import importlib
import json
import logging
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from chisel.core.atomic import atomic_write_texts
from chisel.core.config import seed_list
from chisel.core.errors import InvalidInputError
from chisel.core.mitsuba_variant import load_mitsuba
from chisel.io.manifest import named_path, read_json_manifest
from sim.config import SimConfig, config_to_dict
from sim.errors import ConfigError, PhantomError, SimError
from sim.pipeline import drawn_config, render_phantom

log = logging.getLogger(__name__)

DATASET_FORMAT = "endoscopic-chisel/dataset"
DATASET_VERSION = 1
CARD_FORMAT = "endoscopic-chisel/dataset-card"
CARD_VERSION = 1
INDEX_FILES = ("dataset.json", "dataset_card.json")
"""The index and its card: written together, last, and removed before a rendered seed is
replaced."""
SPLIT_FRACTIONS = {"train": 0.8, "val": 0.1, "test": 0.1}
"""Split by phantom seed: a seed's sequences never straddle two parts."""


def split_by_seed(seeds: list[int]) -> dict[str, list[int]]:
    """Train/val/test by phantom seed: the seeds in order, the last 10 % (at least one when
    there are 3 or more) test, the 10 % before them val, the rest train."""
    ordered = sorted(int(s) for s in seeds)
    n = len(ordered)
    n_test = max(1, round(SPLIT_FRACTIONS["test"] * n)) if n >= 3 else 0
    n_val = max(1, round(SPLIT_FRACTIONS["val"] * n)) if n >= 3 else 0
    n_train = n - n_val - n_test
    return {
        "train": ordered[:n_train],
        "val": ordered[n_train : n_train + n_val],
        "test": ordered[n_train + n_val :],
    }


_DRAWN_KEYS = (
    "appearance.albedo_rgb",
    "appearance.vessel_strength",
    "appearance.roughness",
    "appearance.specular",
    "light.intensity",
    "imaging.exposure",
    "imaging.shot_noise",
    "imaging.read_noise",
    "tools.fraction",
    "smoke.density_per_mm",
    "blur.shutter",
    "lens.smear_probability",
    "blood.strength",
)


def dataset_card(
    dataset: dict[str, Any], command: list[str] | None, renders: dict[int, dict[str, Any]]
) -> dict[str, Any]:
    """The card of a dataset: everything needed to render it again and to use it.

    renders : phantom seed -> that seed's render.json (its config holds the drawn values).
    """
    drawn = {}
    for seed, header in sorted(renders.items()):
        flat = _flat(header["config"])
        drawn[str(seed)] = {"render_seed": flat["seed"], **{k: flat[k] for k in _DRAWN_KEYS}}
    per_kind: dict[str, dict[str, int]] = {}
    for e in dataset["sequences"]:
        c = per_kind.setdefault(e["kind"], {"sequences": 0, "frames": 0})
        c["sequences"] += 1
        c["frames"] += e["num_frames"]
    cfg = dataset["config"]
    return {
        "format": CARD_FORMAT,
        "version": CARD_VERSION,
        "dataset_format": {"format": DATASET_FORMAT, "version": DATASET_VERSION},
        "sequence_format": "chisel.io.sequence (docs/sim.md: render folder)",
        "command": command,
        "reproduce": "run `command` again (same code version): every draw derives from the "
        "phantom seeds, the master seed and the config below",
        "phantom_seeds": dataset["seeds"],
        "master_seed": cfg["seed"],
        "bites": dataset["bites"],
        "ranges": cfg["randomization"],
        "effects_base": {k: cfg[k] for k in ("tools", "smoke", "blur", "lens", "cut", "blood")},
        "drawn": drawn,
        "counts": {
            "phantoms": len(dataset["seeds"]),
            "sequences": dataset["num_sequences"],
            "frames": dataset["num_frames"],
            "by_kind": per_kind,
            "frames_with_tools_enabled": bool(cfg["tools"]["enabled"]),
        },
        "split": split_by_seed(dataset["seeds"]),
        "split_rule": "by phantom seed, sorted: last 10 % test, the 10 % before val, rest train",
        "image": {"width": cfg["camera"]["width"], "height": cfg["camera"]["height"]},
        "config": cfg,
    }


def parse_seeds(text: str) -> list[int]:
    """``"100-119"``, ``"1,4,9"`` or ``"7"`` (and mixtures like ``"1-3,8"``) -> sorted seeds;
    :class:`ConfigError` naming ``--seeds`` otherwise (:func:`chisel.core.config.seed_list`)."""
    try:
        return seed_list(text)
    except ValueError as exc:
        raise ConfigError("--seeds", str(exc)) from None


def _split(option: str, text: str) -> list[str]:
    try:
        return shlex.split(text)
    except ValueError as exc:  # e.g. an unclosed quote
        raise ConfigError(option, f"cannot split {text!r} into arguments: {exc}") from None


class PhantomJob:
    """One run of the phantom generator CLI in a subprocess, started at once and awaited
    with :meth:`wait`, so that :func:`build_dataset` renders one phantom while the next
    is generated (the generator is mostly one core of Python; the renderer leaves time on
    the other). Output goes to a temporary file, not a pipe, so that a chatty generator
    cannot block on a full pipe while nobody reads it.

    ``out_pattern`` names each seed's folder with ``{seed}``. A command of one's own (``phantom_cmd``)
    gets one seed per run (the CLI contract ``--seed S --bites N --out DIR``). The
    default generator gets every seed in one run (``--seeds`` and an ``--out`` pattern:
    its start-up, mostly imports, was half of a phantom's time) and says ``phantom
    written to DIR`` as each folder is complete.
    """

    def __init__(
        self,
        seeds: list[int],
        out_pattern: str,
        bites: int,
        phantom_cmd: str | None = None,
        extra_args: str = "",
        with_ct: bool = False,
    ) -> None:
        if "{seed}" not in out_pattern or not seeds:
            raise ValueError(f"expected seeds and a folder pattern with {{seed}}: {out_pattern!r}")
        out_dirs = {s: Path(out_pattern.replace("{seed}", str(s))) for s in seeds}
        if phantom_cmd:
            base = _split("--phantom-cmd", phantom_cmd)
            if not base:
                raise ConfigError("--phantom-cmd", "empty generator command")
            if len(seeds) != 1:
                raise ValueError("a generator command of one's own runs one seed at a time")
            # the documented contract, in its order: --seed S --bites N --out DIR
            where = [
                "--seed",
                str(seeds[0]),
                "--bites",
                str(bites),
                "--out",
                str(out_dirs[seeds[0]]),
            ]
        else:
            # Rendering needs the meshes only: no CT volumes (about half the generator's
            # time once started) unless asked.
            base = [sys.executable, "-m", "phantoms", "generate"]
            base += [] if with_ct else ["--no-ct"]
            where = ["--seeds", ",".join(map(str, seeds)), "--bites", str(bites)]
            where += ["--out", out_pattern]
        self.out_dirs = out_dirs
        self.cmd = base + where + _split("--phantom-args", extra_args)
        self._log = tempfile.TemporaryFile(mode="w+t")
        try:
            self._proc = subprocess.Popen(
                self.cmd, stdout=self._log, stderr=subprocess.STDOUT, text=True
            )
        except OSError as exc:  # the program itself is missing or not executable
            self._log.close()
            raise PhantomError(
                out_dirs[seeds[0]],
                f"cannot run the phantom generator {base[0]!r}: {exc.strerror or exc}",
            ) from None
        self._one_seed = bool(phantom_cmd)

    def _output(self) -> str:
        self._log.seek(0)
        return self._log.read()

    def wait(self, seed: int) -> Path:
        """``seed``'s phantom folder once it is complete; :class:`PhantomError` with the
        command and the last lines of its output when the generator failed first."""
        out_dir = self.out_dirs[seed]
        done = f"phantom written to {out_dir}\n"
        while True:
            code = self._proc.wait() if self._one_seed else self._proc.poll()
            # the output is read after the exit status: a generator prints before it exits
            reported = (self._one_seed and code == 0) or done in self._output()
            if reported and (out_dir / "phantom.json").is_file():
                return out_dir
            if code is not None:
                tail = " | ".join(self._output().strip().splitlines()[-5:])
                raise PhantomError(
                    out_dir,
                    f"phantom generator failed (exit {code}): {shlex.join(self.cmd)}: {tail}",
                )
            time.sleep(0.05)

    def cancel(self) -> None:
        """Stop a generator that is still running (the build failed or finished)."""
        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.wait()
        self._log.close()


class _PhantomQueue:
    """The phantoms :func:`build_dataset` still has to generate, in order: the default
    generator makes them all in one run, ahead of the renders; a command of one's own
    makes one seed ahead of the render (:class:`PhantomJob`)."""

    def __init__(
        self, pattern: str, bites: int, phantom_cmd: str | None, phantom_args: str, ct: bool
    ) -> None:
        self.pattern, self.bites, self.ct = pattern, bites, ct
        self.phantom_cmd, self.phantom_args = phantom_cmd, phantom_args
        self.to_generate: list[int] = []
        self._jobs: dict[int, PhantomJob] = {}

    def folder(self, seed: int) -> Path:
        return Path(self.pattern.replace("{seed}", str(seed)))

    def start_next(self) -> bool:
        """Start the next generator run unless one is running; True if one started."""
        if not self.to_generate or self._jobs:
            return False
        batch = self.to_generate[:1] if self.phantom_cmd else list(self.to_generate)
        del self.to_generate[: len(batch)]
        job = PhantomJob(
            batch, self.pattern, self.bites, self.phantom_cmd, self.phantom_args, with_ct=self.ct
        )
        self._jobs.update(dict.fromkeys(batch, job))
        return True

    def wait(self, seed: int) -> None:
        """Until ``seed``'s phantom is there (a generated or a kept one), then start the
        next seed's generation, which runs while this one renders."""
        self.start_next()
        if seed in self._jobs:
            job = self._jobs.pop(seed)
            try:
                job.wait(seed)
            finally:
                if job not in self._jobs.values():
                    job.cancel()  # its last seed: close its log
        self.start_next()

    def cancel(self) -> None:
        for job in set(self._jobs.values()):
            job.cancel()
        self._jobs.clear()


def render_seed(phantom_seed: int, master_seed: int) -> int:
    """Master seed of one phantom's render: the phantom seed itself when ``master_seed``
    is 0 (the default), else both mixed by numpy's ``SeedSequence`` (another draw of
    paths, appearance and noise for the same phantoms)."""
    if master_seed == 0:
        return int(phantom_seed)
    return int(np.random.SeedSequence([int(master_seed), int(phantom_seed)]).generate_state(1)[0])


def seed_config(cfg: SimConfig, phantom_seed: int) -> SimConfig:
    """The configuration one phantom of a dataset is rendered with: randomisation on
    (drawn by :func:`sim.pipeline.render_phantom`) and the seed :func:`render_seed`."""
    return dataclasses.replace(
        cfg,
        seed=render_seed(phantom_seed, cfg.seed),
        randomization=dataclasses.replace(cfg.randomization, enabled=True),
    )


def _flat(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _finished_render(header_path: Path, cfg: SimConfig, bites: int) -> dict[str, Any] | None:
    """The render.json of a seed that ``--resume`` may keep, or None to render it again.

    A seed is finished when its render.json reads (through the bounded JSON reader) and
    every sequence it lists is there; a half-deleted one is rendered again, and so is one
    whose render.json is corrupt (with a warning naming it). So is one whose sequence
    names are not plain folder names inside ``seed_S`` (``../x``, an absolute path, a link
    out): nothing outside the seed's folder is read or listed through its render.json. A
    finished seed rendered with other options than this run's is refused: resuming would
    mix them in one dataset.
    """
    if not header_path.exists():
        return None
    try:
        header = read_json_manifest(header_path, SimError)
        sequences = header["sequences"]
        steps = sequences["steps"]
        names = [sequences["preop"], *steps.values()]
        keys = ["sequences.preop", *(f"sequences.steps.{k}" for k in steps)]
        recorded, num_steps = header["config"], int(header["num_steps"])
        for k in steps:  # build_dataset sorts them by number
            if not (k.isascii() and k.isdigit()):
                raise SimError(header_path, f"sequences.steps: a key is not a step number: {k!r}")
        for name, key in zip(names, keys, strict=True):
            _check_sequence_name(header_path, name, key)
    except InvalidInputError as exc:  # unreadable; a name outside seed_S
        log.warning("rendering again: %s", exc)
        return None
    except (ValueError, KeyError, TypeError, AttributeError):
        log.warning("rendering again: %s: not a complete render.json", header_path)
        return None
    if not all((header_path.parent / n / "sequence.json").is_file() for n in names):
        return None
    # Through JSON so that both sides hold lists where the config holds tuples.
    expected = _flat(json.loads(json.dumps(config_to_dict(drawn_config(cfg)))))
    got = _flat(recorded) if isinstance(recorded, dict) else {}
    differ = sorted(k for k in expected.keys() | got.keys() if expected.get(k) != got.get(k))
    if differ or num_steps != bites:
        what = ", ".join(differ + ([] if num_steps == bites else ["bites"]))
        raise ConfigError(
            header_path,
            f"rendered with other options ({what}) than this run; --resume would mix them: "
            "use the same options or another --out",
        )
    return header


def _check_sequence_name(header_path: Path, name: object, key: str) -> None:
    """``name`` (the value of ``key`` in ``header_path``) must be a plain folder name that
    resolves, links followed, to a folder beside ``header_path``; else :class:`SimError`
    naming the file and the key."""
    if not isinstance(name, str) or name in ("", ".", "..") or any(c in name for c in "/\\"):
        raise SimError(header_path, f"{key}: expected a sequence folder name, got {name!r}"[:300])
    root = header_path.absolute().parent.resolve()
    resolved = named_path(header_path, name, key, allow_outside=True)  # a link loop: refused
    if resolved.parent != root:
        raise SimError(header_path, f"{key}: {name!r} is {resolved}, outside {root}"[:400])


def _num_frames(sequence_json: Path) -> int:
    """The frame count a rendered sequence's ``sequence.json`` records."""
    num_frames = read_json_manifest(sequence_json, SimError).get("num_frames")
    if not isinstance(num_frames, int) or isinstance(num_frames, bool) or num_frames < 0:
        raise SimError(sequence_json, f"num_frames: expected an integer >= 0, got {num_frames!r}")
    return num_frames


def build_dataset(
    out_dir: str | Path,
    seeds: list[int],
    cfg: SimConfig,
    bites: int = 2,
    phantom_cmd: str | None = None,
    phantom_args: str = "",
    resume: bool = False,
    progress: bool = True,
    command: list[str] | None = None,
    write_index: bool = True,
    phantom_ct: bool = False,
) -> dict[str, Any]:
    """Generate and render every seed; write and return ``dataset.json``'s content.

    phantom_ct : the default generator also writes each phantom's CT volumes (rendering
    does not need them; ``python -m phantoms generate --no-ct`` otherwise). Ignored with
    ``phantom_cmd``.

    write_index : False renders the seeds only (``seed_S/``, ``phantoms/seed_S/``) and
    writes neither ``dataset.json`` nor the card: one job per seed on a cluster, then one
    ``resume`` run over all seeds that finds them rendered and writes the index.

    ``cfg.randomization`` ranges are sampled once per phantom seed (randomisation is
    switched on here whatever ``cfg.randomization.enabled`` says), with the render seed
    :func:`render_seed` of the phantom seed and ``cfg.seed``. ``dataset_card.json``
    (:func:`dataset_card`) is written with ``dataset.json``; ``command`` is recorded in it.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(out, "the dataset folder exists and is not a folder")
    if "{seed}" in str(out):
        raise ConfigError(
            out, "the dataset folder's path holds '{seed}', the phantom folders' pattern"
        )
    created = _missing_folders(out / "phantoms")
    out.mkdir(parents=True, exist_ok=True)
    try:
        return _build_dataset(
            out, seeds, cfg, bites, phantom_cmd, phantom_args, resume, progress, command,
            write_index, phantom_ct,
        )  # fmt: skip
    except BaseException:
        # A run that failed before its first phantom leaves no empty folder of its own
        # behind; a folder holding anything (a phantom, a render) or made earlier stays.
        _remove_if_empty(created)
        raise


def _missing_folders(path: Path) -> list[Path]:
    """``path`` and those of its parents that do not exist yet, deepest first."""
    missing = []
    for p in (path, *path.parents):
        if p.exists():
            break
        missing.append(p)
    return missing


def _remove_if_empty(folders: list[Path]) -> None:
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty, or gone already
            pass


def _build_dataset(
    out: Path,
    seeds: list[int],
    cfg: SimConfig,
    bites: int,
    phantom_cmd: str | None,
    phantom_args: str,
    resume: bool,
    progress: bool,
    command: list[str] | None,
    write_index: bool,
    phantom_ct: bool,
) -> dict[str, Any]:
    seq_cfgs = {s: seed_config(cfg, s) for s in seeds}
    cfg = dataclasses.replace(
        cfg, randomization=dataclasses.replace(cfg.randomization, enabled=True)
    )
    entries: list[dict[str, Any]] = []
    renders: dict[int, dict[str, Any]] = {}
    finished = {
        s: (
            _finished_render(out / f"seed_{s}" / "render.json", seq_cfgs[s], bites)
            if resume
            else None
        )
        for s in seeds
    }

    pattern = str(out / "phantoms" / "seed_{seed}")
    queue = _PhantomQueue(pattern, bites, phantom_cmd, phantom_args, phantom_ct)
    queue.to_generate = [
        s
        for s in seeds
        if finished[s] is None and not (resume and (queue.folder(s) / "phantom.json").is_file())
    ]

    try:
        if queue.start_next():
            # While the first phantom is made (nothing else to overlap it): the renderer's
            # variant probe and the path planner's Open3D import, ~2 s paid once anyway.
            load_mitsuba(cfg.variant)
            importlib.import_module("open3d")
        for seed in tqdm(seeds, desc="dataset", unit="phantom", disable=not progress):
            render_dir = out / f"seed_{seed}"
            header = finished[seed]
            if header is None:
                queue.wait(seed)
                if render_dir.exists():
                    # This seed's earlier render is about to be replaced: an index left
                    # from the earlier run would then describe renders that are gone, and
                    # a failure later in this run would leave it so. It is rewritten last.
                    for index in INDEX_FILES:
                        (out / index).unlink(missing_ok=True)
                header = render_phantom(
                    queue.folder(seed),
                    render_dir,
                    seq_cfgs[seed],
                    include_eval=False,
                    progress=progress,
                )
                gc.collect()  # the phantom's meshes and scenes in cycles (sim.pipeline)
            renders[int(seed)] = header
            names = [("preop", 0, header["sequences"]["preop"])] + [
                ("intraop", int(k), v)
                for k, v in sorted(header["sequences"]["steps"].items(), key=lambda kv: int(kv[0]))
            ]
            for kind, step, name in names:
                entries.append(
                    {
                        "path": f"seed_{seed}/{name}",
                        "phantom_seed": int(seed),
                        "kind": kind,
                        "step": step,
                        "num_frames": _num_frames(render_dir / name / "sequence.json"),
                    }
                )
    finally:
        queue.cancel()
    dataset = {
        "format": DATASET_FORMAT,
        "version": DATASET_VERSION,
        "seeds": list(seeds),
        "bites": int(bites),
        "num_sequences": len(entries),
        "num_frames": sum(e["num_frames"] for e in entries),
        "sequences": entries,
        "config": config_to_dict(cfg),
    }
    if not write_index:
        return dataset
    card = dataset_card(json.loads(json.dumps(dataset)), command, renders)
    texts = (json.dumps(dataset, indent=2) + "\n", json.dumps(card, indent=2) + "\n")
    atomic_write_texts({out / name: text for name, text in zip(INDEX_FILES, texts, strict=True)})
    return dataset
