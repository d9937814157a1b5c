"""Camera calibration files -> :class:`chisel.core.geometry.Camera`.

Formats read (see docs/real-data.md):

- OpenCV ``cv2.FileStorage`` YAML or XML, as written by OpenCV's calibration samples:
  ``camera_matrix`` (3x3), ``distortion_coefficients`` (1x4, 1x5, or 1x8/12/14 whose
  extra terms are zero), optional ``image_width`` / ``image_height``.
- ROS ``camera_info`` YAML (no ``%YAML:1.0`` header): the same keys, matrices as
  ``{rows, cols, data}`` maps.
- JSON: ``{"width", "height", "K": 3x3 or "fx", "fy", "cx", "cy", "dist": [k1, k2, p1,
  p2, k3]}`` (the ``camera`` block of a sequence's ``sequence.json`` is such a file).

The calibration must be for the resolution of the frames: a file that states its image
size is checked against the frames; one that does not must at least put the principal
point near the image centre. ``rescale=True`` scales ``K`` to frames of the same aspect
ratio at another resolution (distortion coefficients are resolution-free).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from chisel.core.config import read_yaml_mapping
from chisel.core.errors import CameraError, ResourceLimitError
from chisel.core.geometry import Camera
from chisel.io.limits import MAX_IMAGE_SIDE_PX
from chisel.io.manifest import read_json_manifest

_K_KEYS = ("camera_matrix", "K", "cameraMatrix", "intrinsic_matrix")
_DIST_KEYS = ("distortion_coefficients", "dist", "D", "distCoeffs", "dist_coeffs")

MAX_PRINCIPAL_OFFSET = 0.2
"""Largest |cx - centre| / width (and |cy - centre| / height) accepted when the file does
not state its image size; farther means the intrinsics are for another resolution."""


@dataclass(frozen=True)
class Calibration:
    """Intrinsics and distortion as read from a file, before they meet the frames."""

    K: np.ndarray
    """(3, 3) float64 pinhole intrinsics, pixels."""
    dist: np.ndarray
    """(5,) float64 OpenCV k1, k2, p1, p2, k3."""
    size: tuple[int, int] | None
    """(width, height) in pixels the calibration was made at, or None if not stated."""
    source: str
    """The file it came from (for error messages)."""

    def camera_for(self, width: int, height: int, rescale: bool = False) -> Camera:
        """The :class:`Camera` for frames of ``width`` x ``height`` pixels.

        Raises :class:`CameraError` if the calibration is for another resolution (unless
        ``rescale`` and the aspect ratio matches) or its principal point is implausible.
        """
        K = self.K.copy()
        if self.size is not None and self.size != (width, height):
            cw, ch = self.size
            same_aspect = abs(cw * height - ch * width) <= max(cw, width) // 100
            if not (rescale and same_aspect):
                hint = (
                    " (pass rescale / --rescale-intrinsics to scale K)"
                    if same_aspect
                    else " (different aspect ratio: cropped frames need a new calibration)"
                )
                raise CameraError(
                    self.source,
                    f"calibration is for {cw}x{ch} images but the frames are "
                    f"{width}x{height}{hint}",
                )
            # Pixel centres at integer coordinates: x_new + 0.5 = s (x_old + 0.5).
            sx, sy = width / cw, height / ch
            K[0, 0] *= sx
            K[1, 1] *= sy
            K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
            K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        else:
            off_x = abs(K[0, 2] - (width - 1) / 2.0) / width
            off_y = abs(K[1, 2] - (height - 1) / 2.0) / height
            if off_x > MAX_PRINCIPAL_OFFSET or off_y > MAX_PRINCIPAL_OFFSET:
                raise CameraError(
                    self.source,
                    f"principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) is far from the centre "
                    f"of the {width}x{height} frames ({(width - 1) / 2:.1f}, "
                    f"{(height - 1) / 2:.1f}): are these intrinsics for another resolution?",
                )
        try:
            return Camera(width, height, K, self.dist)
        except CameraError as exc:
            raise CameraError(self.source, exc.problem) from None


def _numbers(values: object, what: str, source: str) -> np.ndarray:
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:  # a string or a nested mapping in the file
        raise CameraError(source, f"{what} must be numbers: {exc}") from None


def _number(value: object, key: str, source: str, positive: bool = False) -> float:
    """One finite number (``fx``, ``cy``, ...); ``positive``: also > 0."""
    if isinstance(value, bool):  # np.asarray(True) is 1.0: not a focal length
        raise CameraError(source, f"{key} must be a number, got {value!r}")
    x = _numbers(value, key, source)
    if x.shape != ():
        raise CameraError(source, f"{key} must be a single number, got {value!r}")
    if not np.isfinite(x) or (positive and not x > 0):
        kind = "a positive finite number" if positive else "a finite number"
        raise CameraError(source, f"{key} must be {kind}, got {float(x)}")
    return float(x)


def _pixels(value: object, key: str, source: str) -> int:
    """An image width or height: a positive whole number of pixels (``64.0`` and ``"64"``
    as read before; ``64.5``, ``true``, NaN, inf or a list are refused)."""
    n: int | None = None
    if isinstance(value, str):
        try:
            n = int(value.strip())
        except ValueError:
            n = None
    elif isinstance(value, int) and not isinstance(value, bool):
        n = value
    elif isinstance(value, float) and np.isfinite(value) and value.is_integer():
        n = int(value)
    if n is None or n <= 0:
        raise CameraError(source, f"{key} must be a positive whole number of pixels, got {value!r}")
    if n > MAX_IMAGE_SIDE_PX:
        raise ResourceLimitError(source, f"{key} is {n} px, over the limit of {MAX_IMAGE_SIDE_PX}")
    return n


def _dist5(values: object, source: str) -> np.ndarray:
    d = _numbers(values, "distortion coefficients", source).ravel()
    if d.size == 4:
        d = np.append(d, 0.0)
    elif d.size in (8, 12, 14):
        if np.any(d[5:] != 0.0):
            raise CameraError(
                source,
                f"distortion has {d.size} coefficients with non-zero rational/thin-prism "
                f"terms {d[5:].tolist()}; only the 5-term model (k1, k2, p1, p2, k3) is supported",
            )
        d = d[:5]
    elif d.size != 5:
        raise CameraError(
            source, f"expected 4 or 5 distortion coefficients, got {d.size}: {d.tolist()}"
        )
    if not np.all(np.isfinite(d)):
        raise CameraError(source, f"distortion coefficients are not finite: {d.tolist()}")
    return d


def _matrix3(values: object, source: str) -> np.ndarray:
    K = _numbers(values, "camera matrix", source)
    if K.size != 9:
        raise CameraError(source, f"camera matrix must have 9 entries, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise CameraError(source, f"camera matrix entries must be finite, got {K.ravel().tolist()}")
    return K.reshape(3, 3)


def _from_mapping(d: dict, source: str) -> Calibration:
    """Shared by JSON and ROS-YAML: keys as in the module docstring."""

    def unwrap(v: object) -> object:  # ROS/OpenCV-YAML style {rows, cols, data}
        return v["data"] if isinstance(v, dict) and "data" in v else v

    k_key = next((k for k in _K_KEYS if k in d), None)
    if k_key is not None:
        K = _matrix3(unwrap(d[k_key]), source)
    elif all(k in d for k in ("fx", "fy", "cx", "cy")):
        fx, fy = (_number(d[k], k, source, positive=True) for k in ("fx", "fy"))
        cx, cy = (_number(d[k], k, source) for k in ("cx", "cy"))
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)
    else:
        raise CameraError(
            source, f"no camera matrix: expected one of {list(_K_KEYS)} or fx, fy, cx, cy"
        )
    d_key = next((k for k in _DIST_KEYS if k in d), None)
    dist = _dist5(unwrap(d[d_key]), source) if d_key is not None else np.zeros(5)
    w_key = "width" if "width" in d else "image_width"
    h_key = "height" if "height" in d else "image_height"
    w = None if d.get(w_key) is None else _pixels(d[w_key], w_key, source)
    h = None if d.get(h_key) is None else _pixels(d[h_key], h_key, source)
    size = (w, h) if w is not None and h is not None else None
    return Calibration(K, dist, size, source)


def _read_filestorage(path: Path) -> Calibration | None:
    """OpenCV FileStorage YAML/XML, or None if OpenCV cannot read a matrix from the file."""
    source = str(path)
    try:
        fs = cv2.FileStorage(source, cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):  # OpenCV raises SystemError on some unparsable files
        return None
    try:
        if not fs.isOpened():
            return None

        def mat(keys: tuple[str, ...]) -> np.ndarray | None:
            for k in keys:
                node = fs.getNode(k)
                if not node.empty():
                    # A ROS {rows, cols, data} map is not an opencv-matrix: mat() asserts.
                    return node.mat()
            return None

        K_mat = mat(_K_KEYS)
        if K_mat is None:
            return None
        K = _matrix3(K_mat, source)
        d_mat = mat(_DIST_KEYS)
        dist = np.zeros(5) if d_mat is None else _dist5(d_mat, source)
        w, h = (_fs_pixels(fs.getNode(k), k, source) for k in ("image_width", "image_height"))
        size = (w, h) if w is not None and h is not None else None
        return Calibration(K, dist, size, source)
    except cv2.error:
        return None
    finally:
        fs.release()


def _fs_pixels(node: cv2.FileNode, key: str, source: str) -> int | None:
    """:func:`_pixels` of a FileStorage node, None if absent (``real()`` of a string or a
    sequence is DBL_MAX: the node's type is looked at first)."""
    if node.empty() or node.isNone():
        return None
    if node.isInt() or node.isReal():
        value: object = int(node.real()) if node.isInt() else node.real()
    elif node.isString():
        value = node.string()
    else:
        kind = "a sequence" if node.isSeq() else "a mapping"
        raise CameraError(source, f"{key} must be a positive whole number of pixels, got {kind}")
    return _pixels(value, key, source)


def read_calibration(path: str | Path) -> Calibration:
    """Read intrinsics and distortion from an OpenCV YAML/XML, ROS YAML or JSON file."""
    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise CameraError(source, "calibration file not found")
    suffix = path.suffix.lower()
    if suffix == ".json":
        data = read_json_manifest(path, CameraError)
        if isinstance(data.get("camera"), dict):
            data = data["camera"]  # a sequence.json
        return _from_mapping(data, source)
    if suffix not in (".yaml", ".yml", ".xml"):
        raise CameraError(
            source, f"unknown calibration format {suffix!r}: use .yaml, .xml or .json"
        )
    calib = _read_filestorage(path)
    if calib is not None:
        return calib
    if suffix == ".xml":
        raise CameraError(source, "OpenCV cannot read this XML file or it has no camera_matrix")
    data = read_yaml_mapping(path, CameraError, what="calibration")
    return _from_mapping(data, source)


def write_opencv_calibration(path: str | Path, camera: Camera) -> None:
    """Write ``camera`` as an OpenCV FileStorage YAML/XML (the format OpenCV's samples write)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(camera.width))
        fs.write("image_height", int(camera.height))
        fs.write("camera_matrix", np.asarray(camera.K, dtype=np.float64))
        fs.write("distortion_coefficients", np.asarray(camera.dist, dtype=np.float64)[None, :])
    finally:
        fs.release()
