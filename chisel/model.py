"""The *model* on-disk contract (version 1): a dense TSDF grid with weights.

A model is what the updater keeps current: truncated signed distances ``tsdf`` normalised
by the truncation (+1 = free space in front of the surface, -1 = at least one truncation
behind it), their fusion weights ``weight`` (0 = never observed), optional colour, and
the grid's placement ``T_world_from_voxel`` (voxel index -> voxel *centre* in world mm).

On disk a model is one ``.npz`` file (read with ``allow_pickle=False``)::

    format              str  "endoscopic-chisel/model"
    version             int  1
    tsdf                (X, Y, Z) float32, normalised signed distance in [-1, 1]
    weight              (X, Y, Z) float32, accumulated fusion weight, >= 0
    color               (X, Y, Z, 3) uint8 RGB (optional; absent = no colour)
    T_world_from_voxel  (4, 4) float64, axis-aligned, scaled by the voxel size, mm
    voxel_size_mm       float64 scalar
    trunc_mm            float64 scalar
    step                int64 scalar, surgical steps applied since the preop model (0 = preop)
    build               str  "ct" (initialised from the whole CT) or "sweep" (the paper's
                        build from the preop sweep alone); absent in old files = "sweep"
    ct_sha256           str  content hash of the CT a "ct" build started from ("" = unknown)

Files are written atomically (:func:`chisel.core.atomic.atomic_savez`): a failed save never
leaves a half-written model behind.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from chisel.core.atomic import atomic_savez
from chisel.core.errors import FormatVersionError, InvalidInputError
from chisel.io.limits import (
    MAX_PLACEMENT_MM,
    MAX_VOXEL_SIZE_MM,
    MIN_VOXEL_SIZE_MM,
    read_npz,
)

MODEL_FORMAT = "endoscopic-chisel/model"
MODEL_VERSION = 1

MAX_TRUNC_MM = 1e4
"""Largest truncation distance, mm."""
MAX_STEP = 2**62
"""Steps recorded in a model are below this: ``step`` is saved as int64 and each update
adds one (a uint64 2**64 - 1 read from a file would overflow the next save)."""
BUILDS: tuple[str, ...] = ("ct", "sweep")
"""The preoperative builds a model file can record (field ``build``)."""


@dataclass(frozen=True, eq=False)
class TsdfModel:
    """A dense TSDF volume in world millimetres.

    The dataclass is frozen (fields cannot be rebound) but its arrays are updated in place
    by :mod:`chisel.fusion`; use :meth:`copy` to keep a snapshot.
    """

    tsdf: np.ndarray
    """(X, Y, Z) float32, signed distance / ``trunc_mm`` clipped to [-1, 1]; + = in front."""
    weight: np.ndarray
    """(X, Y, Z) float32, accumulated fusion weight; 0 = unobserved."""
    T_world_from_voxel: np.ndarray
    """(4, 4) float64, voxel index (i, j, k) -> voxel centre in world mm (axis-aligned)."""
    voxel_size_mm: float
    """Edge length of a voxel, mm."""
    trunc_mm: float
    """Truncation distance of the signed distance, mm (``tsdf`` = d / trunc_mm)."""
    color: np.ndarray | None = None
    """(X, Y, Z, 3) uint8 RGB averaged with the same weights, or None."""
    step: int = 0
    """Number of surgical steps applied since the preoperative model (0 = preop)."""
    build: Literal["ct", "sweep"] = "sweep"
    """How the preoperative model was built: "ct" = signed distance of the whole CT plus the
    sweep's weight and colour (:mod:`chisel.ct_model`); "sweep" = the paper's fusion of the
    CT surface rendered at the preop poses."""
    ct_sha256: str = ""
    """sha256 of the CT content the model was initialised from ("" = not recorded)."""

    def __post_init__(self) -> None:
        tsdf = np.asarray(self.tsdf)
        weight = np.asarray(self.weight)
        T = np.asarray(self.T_world_from_voxel)
        # Before the cast: strings would raise numpy's ValueError, complex numbers would
        # lose their imaginary part with only a warning.
        if T.dtype.kind not in "iuf":
            raise InvalidInputError(
                "T_world_from_voxel", f"expected real numbers, got dtype {T.dtype} {T.shape}"
            )
        T = T.astype(np.float64)
        if tsdf.ndim != 3 or tsdf.dtype != np.float32:
            raise InvalidInputError(
                "tsdf", f"expected (X, Y, Z) float32, got {tsdf.shape} {tsdf.dtype}"
            )
        if weight.shape != tsdf.shape or weight.dtype != np.float32:
            raise InvalidInputError(
                "weight", f"expected {tsdf.shape} float32, got {weight.shape} {weight.dtype}"
            )
        if not (self.voxel_size_mm > 0 and np.isfinite(self.voxel_size_mm)):
            raise InvalidInputError("voxel_size_mm", f"must be > 0, got {self.voxel_size_mm}")
        # Bounds, not only signs: a 1e-300 mm voxel or a 1e300 mm placement meshed to
        # collapsed or infinite vertices without an error.
        if not MIN_VOXEL_SIZE_MM <= self.voxel_size_mm <= MAX_VOXEL_SIZE_MM:
            raise InvalidInputError(
                "voxel_size_mm",
                f"must be within [{MIN_VOXEL_SIZE_MM}, {MAX_VOXEL_SIZE_MM}] mm, got "
                f"{self.voxel_size_mm}",
            )
        if not (self.trunc_mm >= self.voxel_size_mm and np.isfinite(self.trunc_mm)):
            raise InvalidInputError(
                "trunc_mm",
                f"must be >= voxel_size_mm ({self.voxel_size_mm}), got {self.trunc_mm}",
            )
        if self.trunc_mm > MAX_TRUNC_MM:
            raise InvalidInputError(
                "trunc_mm", f"must be at most {MAX_TRUNC_MM} mm, got {self.trunc_mm}"
            )
        expected = np.diag([self.voxel_size_mm] * 3 + [1.0])
        expected[:3, 3] = T[:3, 3] if T.shape == (4, 4) else 0.0
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T, expected):
            raise InvalidInputError(
                "T_world_from_voxel",
                "expected an axis-aligned (4, 4) transform scaled by voxel_size_mm "
                f"({self.voxel_size_mm}), got {T.tolist()}",
            )
        far_mm = T[:3, 3] + (np.array(tsdf.shape) - 1) * self.voxel_size_mm
        if max(np.abs(T[:3, 3]).max(), np.abs(far_mm).max()) > MAX_PLACEMENT_MM:
            raise InvalidInputError(
                "T_world_from_voxel",
                f"the grid spans {T[:3, 3].tolist()} to {far_mm.tolist()} mm, beyond "
                f"{MAX_PLACEMENT_MM:g} mm of the world origin: not a patient's CT frame",
            )
        object.__setattr__(self, "T_world_from_voxel", T)
        if self.color is not None:
            c = np.asarray(self.color)
            if c.shape != (*tsdf.shape, 3) or c.dtype != np.uint8:
                raise InvalidInputError(
                    "color", f"expected {(*tsdf.shape, 3)} uint8, got {c.shape} {c.dtype}"
                )
        step = int(self.step)
        if not 0 <= step < MAX_STEP:
            raise InvalidInputError("step", f"must be an integer >= 0 and < 2**62, got {step}")
        object.__setattr__(self, "step", step)
        if self.build not in BUILDS:
            raise InvalidInputError("build", f"expected one of {BUILDS}, got {self.build!r}")

    # ----------------------------------------------------------------- construction
    @classmethod
    def empty(
        cls,
        bounds_min_mm: np.ndarray,
        bounds_max_mm: np.ndarray,
        voxel_size_mm: float,
        trunc_mm: float,
        with_color: bool = False,
    ) -> TsdfModel:
        """An unobserved model (tsdf = 1, weight = 0) covering a world box.

        bounds_min_mm, bounds_max_mm : (3,) float, world mm; the grid covers the box with
        voxel centres starting at ``bounds_min_mm``.
        """
        lo = np.asarray(bounds_min_mm, dtype=np.float64)
        hi = np.asarray(bounds_max_mm, dtype=np.float64)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite([lo, hi])):
            raise InvalidInputError(
                "bounds_mm", f"expected two finite (3,) corners, got {lo}, {hi}"
            )
        if np.any(hi <= lo):
            raise InvalidInputError("bounds_mm", f"empty box: min {lo.tolist()} max {hi.tolist()}")
        if not voxel_size_mm > 0:
            raise InvalidInputError("voxel_size_mm", f"must be > 0, got {voxel_size_mm}")
        dims_f = np.ceil((hi - lo) / voxel_size_mm) + 1
        n_f = float(np.prod(dims_f))  # in floats: a huge box would overflow int64
        if n_f > 400_000_000:
            raise InvalidInputError(
                "voxel_size_mm",
                f"grid of {'x'.join(f'{d:.0f}' for d in dims_f)} voxels ({n_f / 1e6:.0f} M) is too large; "
                "use larger voxels or a smaller region (or a smaller margin)",
            )
        dims = dims_f.astype(np.int64)
        T = np.diag([voxel_size_mm] * 3 + [1.0])
        T[:3, 3] = lo
        shape = tuple(int(d) for d in dims)
        return cls(
            tsdf=np.ones(shape, dtype=np.float32),
            weight=np.zeros(shape, dtype=np.float32),
            T_world_from_voxel=T,
            voxel_size_mm=float(voxel_size_mm),
            trunc_mm=float(trunc_mm),
            color=np.zeros((*shape, 3), dtype=np.uint8) if with_color else None,
        )

    def copy(self) -> TsdfModel:
        """A deep copy (arrays copied)."""
        return replace(
            self,
            tsdf=self.tsdf.copy(),
            weight=self.weight.copy(),
            color=None if self.color is None else self.color.copy(),
        )

    # ----------------------------------------------------------------- geometry
    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.tsdf.shape)  # type: ignore[return-value]

    @property
    def origin_mm(self) -> np.ndarray:
        """(3,) float64 world position of voxel (0, 0, 0)'s centre, mm."""
        return self.T_world_from_voxel[:3, 3].copy()

    @property
    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """World box spanned by the voxel centres: ((3,), (3,)) float64 mm."""
        lo = self.origin_mm
        return lo, lo + (np.array(self.shape) - 1) * self.voxel_size_mm

    def contains_mm(self, point_mm: np.ndarray) -> bool:
        """True if a world point (3,) mm lies inside the grid's box."""
        lo, hi = self.bounds_mm
        p = np.asarray(point_mm, dtype=np.float64)
        return bool(np.all(p >= lo - 1e-9) and np.all(p <= hi + 1e-9))

    def distance_mm(self) -> np.ndarray:
        """(X, Y, Z) float32 truncated signed distance in mm (tsdf * trunc_mm)."""
        return self.tsdf * np.float32(self.trunc_mm)

    # ----------------------------------------------------------------- I/O
    def save(self, path: str | Path) -> Path:
        """Write the model to ``path`` (.npz) atomically; returns ``path``."""
        path = Path(path)
        arrays: dict[str, np.ndarray] = {
            "format": np.array(MODEL_FORMAT),
            "version": np.array(MODEL_VERSION, dtype=np.int64),
            "tsdf": self.tsdf,
            "weight": self.weight,
            "T_world_from_voxel": self.T_world_from_voxel,
            "voxel_size_mm": np.array(self.voxel_size_mm, dtype=np.float64),
            "trunc_mm": np.array(self.trunc_mm, dtype=np.float64),
            "step": np.array(self.step, dtype=np.int64),
            "build": np.array(self.build),
            "ct_sha256": np.array(self.ct_sha256),
        }
        if self.color is not None:
            arrays["color"] = self.color
        return atomic_savez(path, arrays)

    @classmethod
    def load(cls, path: str | Path) -> TsdfModel:
        """Read a model file; raises :class:`FormatVersionError` / :class:`InvalidInputError`."""
        path = Path(path)
        if not path.is_file():
            raise InvalidInputError(path, "model file is missing")
        data = read_npz(path, "model")
        fmt = str(data.get("format", ""))
        if fmt != MODEL_FORMAT:
            raise FormatVersionError(path, f"format is {fmt!r}, expected {MODEL_FORMAT!r}")
        # tolist(): a 0-d integer array gives an int; "1", [1] or 1.5 stay unequal to it.
        version = data["version"].tolist() if "version" in data else None
        if version != MODEL_VERSION:
            raise FormatVersionError(
                path, f"model version {version!r}; this reader reads version {MODEL_VERSION}"
            )
        missing = {"tsdf", "weight", "T_world_from_voxel", "voxel_size_mm", "trunc_mm"} - set(data)
        if missing:
            raise InvalidInputError(path, f"model file lacks field(s) {sorted(missing)}")
        for key in ("voxel_size_mm", "trunc_mm", "step"):
            if key in data and (data[key].shape != () or data[key].dtype.kind not in "iuf"):
                raise InvalidInputError(
                    path, f"{key} must be a single number, got {data[key].dtype} {data[key].shape}"
                )
        # Values, not only shapes: a NaN or out-of-range voxel would spread through fusion
        # and meshing without an error (other dtypes are refused by the constructor below).
        tsdf, weight = data["tsdf"], data["weight"]
        if tsdf.dtype.kind == "f" and not (
            np.all(np.isfinite(tsdf)) and np.abs(tsdf).max(initial=0) <= 1.0
        ):
            raise InvalidInputError(path, "tsdf must be finite and within [-1, 1]")
        if weight.dtype.kind == "f" and not (
            np.all(np.isfinite(weight)) and weight.min(initial=0) >= 0
        ):
            raise InvalidInputError(path, "weight must be finite and >= 0")
        step = data.get("step", np.int64(0))
        if step.dtype.kind not in "iu" or not 0 <= int(step) < MAX_STEP:
            raise InvalidInputError(
                path, f"step must be an integer >= 0 and < 2**62, got {step} ({step.dtype})"
            )
        text = {}
        for key, default in (("build", "sweep"), ("ct_sha256", "")):
            if key in data and (data[key].shape != () or data[key].dtype.kind != "U"):
                raise InvalidInputError(
                    path, f"{key} must be a string, got {data[key].dtype} {data[key].shape}"
                )
            text[key] = str(data[key]) if key in data else default
        try:
            return cls(
                build=text["build"],  # type: ignore[arg-type]
                ct_sha256=text["ct_sha256"],
                tsdf=data["tsdf"],
                weight=data["weight"],
                T_world_from_voxel=data["T_world_from_voxel"],
                voxel_size_mm=float(data["voxel_size_mm"]),
                trunc_mm=float(data["trunc_mm"]),
                color=data.get("color"),
                step=int(step),
            )
        except InvalidInputError as exc:
            raise InvalidInputError(path, f"{exc.source}: {exc.problem}") from None
