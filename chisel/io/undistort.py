"""Undistortion to a pinhole camera and the endoscope's circular field-stop mask.

As the reference implementation's data are prepared: every raw frame is remapped to a
new pinhole camera (``cv2.getOptimalNewCameraMatrix`` + ``cv2.initUndistortRectifyMap``)
with zero distortion, and a mask keeps only the pixels inside the endoscope's circular
field stop (its ``undistorted_mask.bmp``). The field stop is a circle on the *raw*
image (it is a physical aperture in the optics); it is fitted or given there, then
carried through the same remap as the images, so the undistorted mask is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from chisel.core.errors import CameraError, InvalidInputError
from chisel.core.geometry import Camera

FIELD_STOP_MIN_ARC_POINTS = 30
"""Fewest boundary pixels (away from the image border) a field-stop fit accepts."""

NO_FIELD_STOP_FRACTION = 0.97
"""If the bright region covers more than this fraction of the image, there is no dark
border to fit: the frames are taken to have no field stop."""


MAX_RADIAL_SCALE = 10.0
"""Largest factor by which a plausible lens model stretches (or shrinks) image radii."""


def check_lens_model(camera: Camera, used: np.ndarray | None, source: str) -> None:
    """Refuse a distortion model that folds over, or is implausible, where the image is used.

    OpenCV's radial model ``r_d = r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` (normalised radii) is
    fitted to the part of the image a calibration saw; beyond it the polynomial may turn
    back, and there a pixel has two rays and undistortion silently returns one of them.
    Checked out to the farthest ``used`` pixel (the field stop; all pixels when None),
    radial terms only: the tangential ones shift points, they do not fold the image.

    camera : the raw camera. used : (H, W) bool or None. source : named in the error.
    Raises :class:`CameraError` on a fold or a radius scaled by more than
    :data:`MAX_RADIAL_SCALE` (coefficients for another normalisation, say).
    """
    if not camera.has_distortion:
        return
    k1, k2, _, _, k3 = (float(k) for k in camera.dist)
    if used is None:  # the farthest pixels are corners
        u = np.array([0.0, camera.width - 1.0, 0.0, camera.width - 1.0])
        v = np.array([0.0, 0.0, camera.height - 1.0, camera.height - 1.0])
    else:
        v, u = np.nonzero(used)
        if u.size == 0:
            return
    rd_used = float(np.hypot((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy).max())
    f_px = 0.5 * (camera.fx + camera.fy)
    # Undistorted radius = tan(angle off the axis): 0 .. 1e3 (89.94 degrees).
    r = np.concatenate([[0.0], np.geomspace(1e-6, 1e3, 4001)])  # steps of 0.5 %
    r2 = r * r
    rd = r * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
    slope = 1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3))
    turn = np.flatnonzero(slope <= 0.0)
    end = int(turn[0]) if len(turn) else len(r)
    coeffs = f"k1, k2, k3 = {k1:g}, {k2:g}, {k3:g}"
    if rd[:end].max() < rd_used:
        raise CameraError(
            source,
            f"the distortion model ({coeffs}) turns back {rd[:end].max() * f_px:.0f} px from "
            f"the principal point, inside the used image (out to {rd_used * f_px:.0f} px): "
            "pixels there have no single ray; calibrate over the whole field of view, or "
            "give the field stop so that only its pixels are used",
        )
    inside = slice(1, int(np.searchsorted(rd[:end], rd_used)) + 1)
    scale = rd[inside] / r[inside]
    worst = float(scale.max() if scale.max() > 1.0 / scale.min() else scale.min())
    if not 1.0 / MAX_RADIAL_SCALE <= worst <= MAX_RADIAL_SCALE:
        raise CameraError(
            source,
            f"the distortion model ({coeffs}) scales image radii by {worst:.3g} inside the "
            f"used image: not a plausible lens (coefficients for another normalisation?)",
        )


@dataclass(frozen=True)
class Undistortion:
    """A fixed remap from a distorted camera's raw images to a pinhole camera's images."""

    raw: Camera
    """The physical camera (with distortion) the raw frames come from."""
    camera: Camera
    """The new pinhole camera (zero distortion) of the undistorted frames."""
    map_x: np.ndarray
    """(H, W) float32: raw-image u sampled for each undistorted pixel."""
    map_y: np.ndarray
    """(H, W) float32: raw-image v sampled for each undistorted pixel."""
    valid: np.ndarray
    """(H, W) bool: undistorted pixels whose sample lies inside the raw image."""

    def image(self, rgb: np.ndarray) -> np.ndarray:
        """rgb : (H, W, 3) uint8 raw image. Returns (H, W, 3) uint8, bilinear, 0 outside."""
        self.raw.check_image(rgb, "image")
        return cv2.remap(
            rgb, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
        )

    def mask(self, mask: np.ndarray) -> np.ndarray:
        """mask : (H, W) bool on the raw grid. Returns (H, W) bool, nearest, False outside."""
        self.raw.check_image(mask, "mask")
        m = cv2.remap(
            np.asarray(mask, np.uint8),
            self.map_x,
            self.map_y,
            cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT,
        )
        return (m > 0) & self.valid

    def depth(self, depth_mm: np.ndarray) -> np.ndarray:
        """depth_mm : (H, W) float32 raw-grid z-depth, NaN invalid. Returns the same, undistorted.

        z-depth belongs to the 3-D point, not to the pixel, so it is resampled unchanged;
        nearest sampling keeps depth edges from blending foreground and background.
        """
        self.raw.check_image(depth_mm, "depth_mm")
        d = cv2.remap(
            np.asarray(depth_mm, np.float32),
            self.map_x,
            self.map_y,
            cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=float("nan"),
        )
        d[~self.valid] = np.nan
        return d

    def points_to_undistorted(self, uv_raw: np.ndarray) -> np.ndarray:
        """uv_raw : (N, 2) float raw pixels. Returns (N, 2) float64 pixels of :attr:`camera`."""
        pts = np.asarray(uv_raw, np.float64).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        out = cv2.undistortPoints(
            pts, self.raw.K, self.raw.dist, None, None, self.camera.K, criteria
        )
        return out.reshape(-1, 2)

    def points_to_raw(self, uv_undistorted: np.ndarray) -> np.ndarray:
        """uv_undistorted : (N, 2) pixels of :attr:`camera`. Returns (N, 2) raw pixels."""
        uv = np.asarray(uv_undistorted, np.float64).reshape(-1, 2)
        x = (uv[:, 0] - self.camera.cx) / self.camera.fx
        y = (uv[:, 1] - self.camera.cy) / self.camera.fy
        return self.raw.project(np.stack([x, y, np.ones_like(x)], axis=-1))[0]


def make_undistortion(raw: Camera, alpha: float = 0.0) -> Undistortion:
    """The remap from ``raw`` to a pinhole camera of the same size.

    alpha : OpenCV's free-scaling parameter in [0, 1]: 0 keeps only valid pixels (crops the
    black corners), 1 keeps every raw pixel (black corners stay). Endoscope frames are
    round, so 0 loses nothing that the field stop does not already hide.
    """
    if not 0.0 <= alpha <= 1.0:
        raise CameraError("alpha", f"must be in [0, 1], got {alpha}")
    size = (int(raw.width), int(raw.height))
    new_K, _roi = cv2.getOptimalNewCameraMatrix(raw.K, raw.dist, size, alpha, size)
    new_K = np.asarray(new_K, np.float64)
    new_K[0, 1] = new_K[1, 0] = 0.0  # OpenCV returns no skew; make it exact
    new_K[2] = [0.0, 0.0, 1.0]
    camera = Camera(raw.width, raw.height, new_K, np.zeros(5))
    map_x, map_y = cv2.initUndistortRectifyMap(raw.K, raw.dist, None, new_K, size, cv2.CV_32FC1)
    valid = (
        (map_x >= -0.5) & (map_x <= raw.width - 0.5) & (map_y >= -0.5) & (map_y <= raw.height - 0.5)
    )
    return Undistortion(raw, camera, map_x, map_y, valid)


@dataclass(frozen=True)
class Circle:
    """A circle in pixel coordinates (pixel centres at integers)."""

    cx: float
    """Centre column, pixels."""
    cy: float
    """Centre row, pixels."""
    r: float
    """Radius, pixels."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.cx) and np.isfinite(self.cy) and np.isfinite(self.r)):
            raise InvalidInputError("circle", f"values must be finite, got {self}")
        if self.r <= 0:
            raise InvalidInputError("circle", f"radius must be positive, got {self.r}")

    @classmethod
    def parse(cls, text: str, source: str = "circle") -> Circle:
        """``"cx,cy,r"`` in pixels -> Circle."""
        try:
            cx, cy, r = (float(v) for v in text.split(","))
        except ValueError:
            raise InvalidInputError(source, f"expected 'cx,cy,r' in pixels, got {text!r}") from None
        return cls(cx, cy, r)


def circle_mask(shape: tuple[int, int], circle: Circle, margin_px: float = 0.0) -> np.ndarray:
    """(H, W) bool: pixel centres within ``circle.r - margin_px`` of the centre."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]]
    r = circle.r - margin_px
    if r < 0:  # r * r below would turn a margin wider than the circle into a circle
        return np.zeros(shape, dtype=bool)
    return (u - circle.cx) ** 2 + (v - circle.cy) ** 2 <= r * r


def _fit_circle(points: np.ndarray) -> Circle:
    """Least-squares circle through (N, 2) points: the algebraic (Kasa) fit, refined by
    minimising the geometric distances (Kasa alone shrinks circles fitted to short arcs)."""
    x, y = points[:, 0], points[:, 1]
    A = np.stack([x, y, np.ones_like(x)], axis=1)
    b = -(x * x + y * y)
    (D, E, F), *_ = np.linalg.lstsq(A, b, rcond=None)
    cx, cy = -D / 2.0, -E / 2.0
    r = float(np.sqrt(max(cx * cx + cy * cy - F, 1e-12)))

    def residual(p: np.ndarray) -> np.ndarray:
        return np.hypot(x - p[0], y - p[1]) - p[2]

    sol = least_squares(residual, np.array([cx, cy, r]), method="lm")
    return Circle(float(sol.x[0]), float(sol.x[1]), float(abs(sol.x[2])))


def fit_field_stop(images: list[np.ndarray]) -> Circle | None:
    """Fit the endoscope's circular field stop to the bright region of some raw frames.

    images : list of (H, W, 3) uint8 RGB raw frames (a few dozen are plenty).
    Returns the circle in raw pixels, or None when the frames have no dark border.
    The per-pixel maximum over frames is thresholded (Otsu); the outline of the largest
    bright component is fitted by least squares, ignoring outline points on the image
    border (a field stop wider than the image is clipped there) and, refitting, points
    more than 1 px inside the fit (notches of dark anatomy at the rim).
    """
    if not images:
        raise InvalidInputError("field stop", "no frames to fit the field stop to")
    gray = np.max(
        np.stack([cv2.cvtColor(np.asarray(im, np.uint8), cv2.COLOR_RGB2GRAY) for im in images]),
        axis=0,
    )
    h, w = gray.shape
    if int(gray.max()) == int(gray.min()):
        raise InvalidInputError("field stop", "frames are uniform: nothing to fit")
    _, bright = cv2.threshold(gray, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    # Dark speckle inside the field of view frays the rim; closing mends it and leaves a
    # convex outline (the circle) unchanged.
    bright = cv2.morphologyEx(
        bright, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    )
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bright, connectivity=8)
    if n < 2:
        raise InvalidInputError("field stop", "no bright region in the frames")
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    region = (labels == largest).astype(np.uint8)
    contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    outline = max(contours, key=len)
    if cv2.contourArea(outline) > NO_FIELD_STOP_FRACTION * h * w:
        return None
    pts = outline.reshape(-1, 2).astype(np.float64)
    on_border = (pts[:, 0] <= 0) | (pts[:, 1] <= 0) | (pts[:, 0] >= w - 1) | (pts[:, 1] >= h - 1)
    pts = pts[~on_border]
    if len(pts) < FIELD_STOP_MIN_ARC_POINTS:
        raise InvalidInputError(
            "field stop",
            f"only {len(pts)} outline pixels off the image border (need "
            f"{FIELD_STOP_MIN_ARC_POINTS}); give the circle explicitly",
        )
    circle = _fit_circle(pts)
    # Dark anatomy at the rim cuts notches into the bright region: their outline points lie
    # inside the circle. Refit without them until the set is stable.
    for _ in range(3):
        keep = np.hypot(pts[:, 0] - circle.cx, pts[:, 1] - circle.cy) > circle.r - 1.0
        if keep.all() or keep.sum() < FIELD_STOP_MIN_ARC_POINTS:
            break
        pts = pts[keep]
        circle = _fit_circle(pts)
    # Outline pixels are the outermost bright pixel centres: on average half a pixel inside
    # the rim (measured over random discs in tests/test_properties.py).
    return Circle(circle.cx, circle.cy, circle.r + 0.5)
