"""Depth from a researcher's own estimator, as a depth sequence the updater reads.

Two kinds, each written as a NEW sequence folder (the input's RGB, masks and poses, the
estimator's depth) that ``chisel update --depth-source sequence:DIR`` reads
(:class:`chisel.depth_source.SequenceDepth`):

- an exported **TorchScript** module with :class:`chisel.depth.network.DepthPredictor`'s
  contract: ``(B, H, W, 3)`` uint8 RGB in, ``(B, H, W)`` float32 depth out;
- a **command**, one line split like a shell's (no pipes: for a shell, pass the folders as
  its arguments, ``bash -c 'est.py "$1" "$2"' _ {input} {output}``) with ``{input}`` and
  ``{output}`` in it, each a whole argument: ``{input}`` is the sequence folder
  (``sequence.json``, ``poses.txt``, ``rgb/NNNNNN.png``, ``mask/NNNNNN.png``), ``{output}``
  an empty folder in which it writes ``NNNNNN.npy`` per frame, (H, W) float32 z-depth,
  NaN or <= 0 = invalid.

``metric``: the depth is millimetres (the updater keeps its scale), else it is up to an
unknown scale (the updater solves it per frame, as for the project's own network); a
relative map is rescaled to a median of :data:`RELATIVE_MEDIAN` (its unit is arbitrary
anyway) so that the sequence reader's metres check does not take it for metres.
"""

from __future__ import annotations

import shlex
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from chisel.core.errors import InvalidInputError
from chisel.depth.infer import load_depth_source, predict_sequence
from chisel.io.import_common import load_npy
from chisel.io.sequence import Frame, Sequence

RELATIVE_MEDIAN = 10.0
"""Median of a relative depth map as written (arbitrary unit; the updater solves the scale)."""

DEFAULT_TIMEOUT_S = 3600.0
"""A command that runs longer than this on one sequence is stopped (an error)."""


class _Relative:
    """Rescales a relative estimator's maps to a median of :data:`RELATIVE_MEDIAN`."""

    def __init__(self, source: object) -> None:
        self.source = source

    def __call__(self, frame: Frame) -> np.ndarray:
        d = np.asarray(self.source(frame), dtype=np.float32)  # type: ignore[operator]
        d = np.where(np.isfinite(d) & (d > 0), d, np.float32(np.nan))
        if not np.isfinite(d).any():
            return d
        return (d * np.float32(RELATIVE_MEDIAN / float(np.nanmedian(d)))).astype(np.float32)


class _ModuleDepth:
    """An exported module's depth; what goes wrong inside it is named after its file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.source = load_depth_source(path)

    def __call__(self, frame: Frame) -> np.ndarray:
        try:
            d = self.source(frame)
        except InvalidInputError:
            raise  # already names the file (an output that breaks the contract, say)
        except (RuntimeError, TypeError, ValueError, IndexError, AttributeError) as exc:
            # TorchScript raises RuntimeError (torch.jit.Error); an eager module anything.
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise InvalidInputError(
                self.path, f"the model failed on frame {frame.index}: {first}"
            ) from None
        assert frame.rgb is not None  # the source read it
        if d.shape != frame.rgb.shape[:2]:
            raise InvalidInputError(
                self.path,
                f"returned depth of shape {d.shape} for a {frame.rgb.shape[0]}x"
                f"{frame.rgb.shape[1]} image; expected (B, H, W) for (B, H, W, 3) input",
            )
        return d


class _FolderDepth:
    """The depth maps a command wrote: ``NNNNNN.npy`` per frame of the sequence."""

    def __init__(self, folder: Path, command: str, shape: tuple[int, int]) -> None:
        self.folder = folder.resolve()
        self.command = command
        self.shape = shape

    def __call__(self, frame: Frame) -> np.ndarray:
        path = self.folder / f"{frame.index:06d}.npy"
        if not path.is_file():
            raise InvalidInputError(
                path, f"the depth command did not write this frame's depth ({self.command!r})"
            )
        if path.resolve().parent != self.folder:
            raise InvalidInputError(path, "is a link out of the command's output folder")
        d = load_npy(path)
        if d.dtype.kind != "f" or d.shape != self.shape:
            raise InvalidInputError(
                path, f"expected a {self.shape} (H, W) float depth map, got {d.dtype} {d.shape}"
            )
        return d.astype(np.float32)


PLACEHOLDERS = ("{input}", "{output}")
"""What a command names the two folders by; each must be one whole argument of its own."""


def command_line(command: str, input_dir: Path, output_dir: Path) -> list[str]:
    """The command's argv: each ``{input}`` and ``{output}`` argument replaced by its folder.

    Each placeholder must be a whole argument (``est.py {input} {output}``), so that a
    folder's name reaches the estimator as one argument whatever it holds: spaces, quotes
    or ``$(...)`` are never read by a shell. A placeholder inside a longer argument
    (``bash -c 'est.py {input} {output}'``, ``--in={input}``) is refused: pasted into a
    shell's ``-c`` script the folder name would be run as shell code. Through a shell,
    pass the folders as its positional parameters:
    ``bash -c 'python est.py "$1" "$2"' _ {input} {output}``.
    """
    source = "--command"  # the workflow's depth.extra.<name>.command arrives as this option
    try:
        argv = shlex.split(command)
    except ValueError as exc:
        raise InvalidInputError(source, f"cannot split {command!r}: {exc}") from None
    embedded = [a for a in argv if a not in PLACEHOLDERS and any(p in a for p in PLACEHOLDERS)]
    if embedded:
        raise InvalidInputError(
            source,
            f"{{input}} and {{output}} must each be a whole argument, got {embedded[0]!r} in "
            f"{command!r} (config depth.extra.<name>.command): a folder name pasted into a "
            "longer argument would be shell code under bash -c; pass the folders as the "
            """shell's arguments instead: bash -c 'python est.py "$1" "$2"' _ {input} {output}""",
        )
    for placeholder in PLACEHOLDERS:
        if placeholder not in argv:
            raise InvalidInputError(
                source,
                f"must contain {{input}} and {{output}}, each as an argument of its own "
                f"(no {placeholder} argument in {command!r})",
            )
    folders = {"{input}": str(input_dir), "{output}": str(output_dir)}
    return [folders.get(a, a) for a in argv]


def run_command(
    command: str, sequence_dir: Path, output_dir: Path, timeout_s: float = DEFAULT_TIMEOUT_S
) -> None:
    """Run the estimator's command on one sequence; raises naming it when it fails."""
    argv = command_line(command, sequence_dir, output_dir)
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s, check=False)
    except FileNotFoundError:
        raise InvalidInputError("command", f"{argv[0]!r} not found ({command!r})") from None
    except subprocess.TimeoutExpired:
        raise InvalidInputError(
            "command", f"{command!r} ran longer than {timeout_s:g} s on {sequence_dir}"
        ) from None
    if proc.returncode != 0:
        tail = "\n".join(proc.stderr.strip().splitlines()[-5:])
        raise InvalidInputError(
            "command", f"{command!r} exited with {proc.returncode} on {sequence_dir}: {tail}"
        )


def external_depth(
    sequence: Sequence,
    out: str | Path,
    *,
    torchscript: str | Path | None = None,
    command: str | None = None,
    metric: bool = False,
    timeout_s: float = DEFAULT_TIMEOUT_S,
) -> Path:
    """Write ``out``: ``sequence`` with the external estimator's depth (atomically).

    Exactly one of ``torchscript`` (an exported module) and ``command`` (a line with
    ``{input}`` and ``{output}``) is given.
    """
    if (torchscript is None) == (command is None):
        raise InvalidInputError("estimator", "give exactly one of a TorchScript file and a command")
    meta: dict[str, object] = {"relative_depth": not metric}
    with tempfile.TemporaryDirectory(prefix="chisel-extern-") as tmp:
        if torchscript is not None:
            source: object = _ModuleDepth(Path(torchscript))
            meta["model"] = str(torchscript)
        else:
            assert command is not None
            folder = Path(tmp) / "depth"
            folder.mkdir()
            run_command(command, sequence.path, folder, timeout_s)
            source = _FolderDepth(folder, command, sequence.camera.shape)
            meta["command"] = command
        if not metric:
            source = _Relative(source)
            meta["relative_median"] = RELATIVE_MEDIAN
        return predict_sequence(source, sequence, out, meta=meta)  # type: ignore[arg-type]
