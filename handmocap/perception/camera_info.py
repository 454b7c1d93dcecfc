"""Camera intrinsics: the one place that makes, loads, scales and publishes them.

Conventions (messages/CameraInfo.json; docs/reference.md): pixels, origin top-left, x right, y down; pixel centres at integer
coordinates, as in OpenCV, so the centre of a W×H image is ((W-1)/2, (H-1)/2).
K is (3,3) float64 [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels; distortion is OpenCV's
(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, τx, τy]]]]), float64 (n,), n in {4, 5, 8, 12, 14}.

Calibration files `load_calibration` reads:
- YAML or JSON with `K` (3x3 nested list, or [fx, fy, cx, cy]), optional `distortion`
  (list), optional `width` and `height` (the image size the calibration was made at);
- ROS camera_calibration's `ost.yaml` (`image_width`, `image_height`,
  `camera_matrix: {rows, cols, data}`, `distortion_model`, `distortion_coefficients`);
- OpenCV FileStorage YAML/XML/JSON as written by `cv2.FileStorage` (OpenCV's calibration
  sample: `image_width`, `image_height`, `camera_matrix`, `distortion_coefficients`);
- `.npy` holding a (3,3) K or a (4,) fx, fy, cx, cy (no size, no distortion).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import yaml

DEFAULT_HFOV_DEG = 60.0
"""Horizontal field of view assumed when nothing better is known: a typical laptop or USB
webcam sees 55-70 degrees across (e.g. 78 degrees diagonal is about 70 across at 16:9)."""

OPENCV_DISTORTION_LENGTHS = (4, 5, 8, 12, 14)
ASPECT_TOLERANCE = 0.01   # relative difference of width/height ratios still called "the same"


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera: K (3,3) float64 px, distortion (n,) float64, and the image size
    (width, height) px K belongs to (None: unknown, K is used as is). `source` says where it
    came from: 'calibration', 'device' or 'default-fov' (the CameraInfo field)."""
    K: np.ndarray
    distortion: np.ndarray
    size: tuple[int, int] | None
    source: str

    def for_size(self, width: int, height: int) -> Intrinsics:
        """These intrinsics for frames of width×height px: scaled when the calibration was made
        at another size of the same aspect ratio (a resized image, not a crop). Raises
        ValueError when the aspect ratios differ, or, for an unknown size, when the principal
        point lies outside the frame (a calibration made at another size)."""
        if self.size is None:
            cx, cy = self.K[0, 2], self.K[1, 2]
            if not (0 <= cx < width and 0 <= cy < height):
                raise ValueError(f"principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} frame: "
                                 f"the calibration was made at another image size; give its width and height")
            return self
        if self.size == (width, height):
            return self
        return replace(self, K=scale_K(self.K, self.size, (width, height)), size=(width, height))


def project(K, xyz) -> np.ndarray:
    """Pinhole projection, no lens distortion, camera-frame points in metres -> pixels:
    K (3,3) with points (...,3) -> (...,2); or one K per set, K (...,3,3) with points
    (...,P,3) -> (...,P,2). inf/NaN where z = 0."""
    K, xyz = np.asarray(K, np.float64), np.asarray(xyz, np.float64)
    p = xyz @ K.T if K.ndim == 2 else np.einsum("...ij,...nj->...ni", K, xyz)
    with np.errstate(invalid="ignore", divide="ignore"):
        return p[..., :2] / p[..., 2:3]


def default_K(width: int, height: int, hfov_deg: float = DEFAULT_HFOV_DEG) -> np.ndarray:
    """K (3,3) float64 of an ideal camera with horizontal field of view `hfov_deg` across the
    full image width, square pixels, principal point at the image centre."""
    if not 0 < hfov_deg < 180:
        raise ValueError(f"field of view must be in (0, 180) degrees, got {hfov_deg}")
    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def default_intrinsics(width: int, height: int, hfov_deg: float = DEFAULT_HFOV_DEG) -> Intrinsics:
    """`default_K` with no distortion, source 'default-fov'."""
    return Intrinsics(default_K(width, height, hfov_deg), np.zeros(5), (width, height), "default-fov")


def scale_K(K: np.ndarray, from_size: tuple[int, int], to_size: tuple[int, int]) -> np.ndarray:
    """K (3,3) of an image resized from `from_size` to `to_size` (width, height) px.

    The aspect ratios must match (raises ValueError otherwise: a crop needs more than a scale).
    Pixel centres map as u' + 0.5 = (u + 0.5) * s, as cv2.resize does."""
    (w0, h0), (w1, h1) = from_size, to_size
    if abs((w1 / h1) / (w0 / h0) - 1.0) > ASPECT_TOLERANCE:
        g = math.gcd(w0, h0)
        raise ValueError(f"calibration is for {w0}x{h0} but frames are {w1}x{h1}: a different aspect ratio "
                         f"(a crop, not a resize); calibrate at this size or use a {w0 // g}:{h0 // g} frame size")
    sx, sy = w1 / w0, h1 / h0
    out = np.array(K, dtype=np.float64)
    out[0, 0] *= sx
    out[0, 1] *= sx
    out[1, 1] *= sy
    out[0, 2] = (out[0, 2] + 0.5) * sx - 0.5
    out[1, 2] = (out[1, 2] + 0.5) * sy - 0.5
    return out


def as_K(values, what: str = "K") -> np.ndarray:
    """A (3,3) K from a 3x3 matrix (or its 9 row-major numbers) or a (4,) fx, fy, cx, cy.
    Raises ValueError naming the problem: wrong shape, NaN/inf, non-positive focal length,
    a last row other than (0, 0, 1)."""
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} is not a matrix of numbers") from None
    if a.shape == (4,):
        fx, fy, cx, cy = a
        a = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    elif a.shape == (9,):
        a = a.reshape(3, 3)
    if a.shape != (3, 3):
        raise ValueError(f"{what} has shape {a.shape}, expected (3, 3) or (4,) fx, fy, cx, cy")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} contains NaN or infinite values")
    if a[0, 0] <= 0 or a[1, 1] <= 0:
        raise ValueError(f"{what} has a non-positive focal length (fx={a[0, 0]:g}, fy={a[1, 1]:g})")
    if not np.allclose(a[2], (0.0, 0.0, 1.0)) or a[1, 0] != 0:
        raise ValueError(f"{what} is not an intrinsic matrix: expected rows [fx, s, cx], [0, fy, cy], [0, 0, 1]")
    return a


def as_distortion(values) -> np.ndarray:
    """OpenCV distortion coefficients, float64 (n,); None or empty means none (zeros(5))."""
    if values is None:
        return np.zeros(5)
    try:
        d = np.asarray(values, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise ValueError("distortion is not a list of numbers") from None
    if d.size == 0:
        return np.zeros(5)
    if d.size not in OPENCV_DISTORTION_LENGTHS:
        raise ValueError(f"distortion has {d.size} coefficients, expected one of {OPENCV_DISTORTION_LENGTHS} "
                         f"(OpenCV's k1, k2, p1, p2[, k3 ...])")
    if not np.all(np.isfinite(d)):
        raise ValueError("distortion contains NaN or infinite values")
    return d


def check_calibration_param(node: str, value) -> None:
    """A node's `calibration` param (for its `check_params`): null, or a file that
    load_calibration reads as the node will; ValueError naming the node and the param."""
    if value is not None:
        try:
            load_calibration(value)
        except ValueError as e:
            raise ValueError(f"{node} param calibration: {e}") from None


def load_calibration(path: str | Path) -> Intrinsics:
    """Read a calibration file (formats: see the module docstring), source 'calibration'.
    Any problem raises one ValueError naming the file and the problem."""
    path = Path(path)
    try:
        K, dist, size = _read(path)
        return Intrinsics(as_K(K), as_distortion(dist), _size(size), "calibration")
    except ValueError as e:
        raise ValueError(f"calibration file {path}: {e}") from None


def _size(size) -> tuple[int, int] | None:
    w, h = size
    if w is None and h is None:
        return None
    if w is None or h is None:
        raise ValueError("gives only one of width and height")
    try:
        w, h = int(w), int(h)
    except (TypeError, ValueError):
        raise ValueError(f"width/height {size!r} are not integers") from None
    if w <= 0 or h <= 0:
        raise ValueError(f"image size {w}x{h} is not positive")
    return w, h


def _read(path: Path):
    """(K-like, distortion-like or None, (width, height) or (None, None)) from the file."""
    if not path.is_file():
        raise ValueError("no such file")
    if path.suffix.lower() == ".npy":
        try:
            return np.load(path, allow_pickle=False), None, (None, None)
        except (OSError, ValueError) as e:
            raise ValueError(f"unreadable .npy: {e}") from None
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise ValueError(f"unreadable: {e}") from None
    if text.lstrip().startswith(("%YAML", "<?xml", "<opencv_storage")) or "!!opencv-matrix" in text:
        return _read_opencv_storage(path)
    try:
        doc = yaml.safe_load(text)   # YAML is a superset of JSON: this reads both
    except yaml.YAMLError as e:
        raise ValueError(f"malformed YAML/JSON: {getattr(e, 'problem', None) or e}") from None
    if not isinstance(doc, dict):
        raise ValueError("expected a mapping with K (or camera_matrix) at the top level")
    if "K" in doc:
        return doc["K"], doc.get("distortion"), (doc.get("width"), doc.get("height"))
    if "camera_matrix" in doc:   # ROS camera_calibration ost.yaml
        model = doc.get("distortion_model", "plumb_bob")
        if model not in ("plumb_bob", "rational_polynomial"):
            raise ValueError(f"distortion_model {model!r} is not OpenCV's pinhole model "
                             f"(plumb_bob or rational_polynomial)")
        dist = doc.get("distortion_coefficients")
        return (_ros_matrix(doc["camera_matrix"], "camera_matrix"),
                None if dist is None else _ros_matrix(dist, "distortion_coefficients"),
                (doc.get("image_width"), doc.get("image_height")))
    raise ValueError(f"no K or camera_matrix key (keys: {', '.join(map(str, doc)) or 'none'})")


def _ros_matrix(m, what: str):
    """`{rows, cols, data}` (ROS) or a plain list."""
    if isinstance(m, dict):
        if "data" not in m:
            raise ValueError(f"{what} has no data")
        return m["data"]
    return m


def _read_opencv_storage(path: Path):
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise ValueError(f"unreadable OpenCV FileStorage: {e.err}") from None
    try:
        if not fs.isOpened():
            raise ValueError("unreadable OpenCV FileStorage")
        k_node = fs.getNode("camera_matrix")
        if k_node.empty():
            raise ValueError("OpenCV FileStorage without camera_matrix")
        K = k_node.mat()
        if K is None:
            raise ValueError("camera_matrix is not an opencv-matrix")
        d_node = fs.getNode("distortion_coefficients")
        dist = None if d_node.empty() else d_node.mat()
        w, h = fs.getNode("image_width"), fs.getNode("image_height")
        size = (None if w.empty() else int(w.real()), None if h.empty() else int(h.real()))
        return K, dist, size
    finally:
        fs.release()


def camera_info_message(K: np.ndarray, distortion: np.ndarray, width: int, height: int, source: str) -> dict:
    """The CameraInfo body (no header): K (3,3) float64 px, distortion (n,) float64, the frame
    size in px and where K came from."""
    return {"width": int(width), "height": int(height),
            "K": np.ascontiguousarray(K, dtype=np.float64).reshape(3, 3),
            "distortion": np.ascontiguousarray(distortion, dtype=np.float64).ravel(),
            "source": source}


def intrinsics_for_frames(width: int, height: int, calibration: str | Path | None = None) -> Intrinsics:
    """What a camera source publishes for width×height frames: the calibration file scaled to
    that size when given, else `default_intrinsics`."""
    if calibration is None:
        return default_intrinsics(width, height)
    intr = load_calibration(calibration)
    try:
        return intr.for_size(width, height)
    except ValueError as e:
        raise ValueError(f"calibration file {calibration}: {e}") from None
