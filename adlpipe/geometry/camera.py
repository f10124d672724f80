"""What adlpipe knows about a camera beyond its pinhole: the lens distortion of sensor_msgs/CameraInfo, and the one
projection of base-frame points to the pixels where they appear in the stored (distorted) image, by OpenCV.

ROS names three models: plumb_bob (k1, k2, p1, p2, k3), rational_polynomial (k1, k2, p1, p2, k3, k4, k5, k6; the
Azure Kinect's) and equidistant (k1..k4, the fisheye model: cv2.fisheye). The coefficients act on normalised image
coordinates, so resizing the image (scaling K) keeps them valid.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..plumbing.errors import AdlError
from .transforms import in_camera, pinhole

COEFFICIENTS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}


@dataclass(frozen=True)
class Lens:
    """A distortion model and its coefficients; Lens() (no model) is the undistorted pinhole."""

    model: str = ""
    D: tuple[float, ...] = ()

    @property
    def distorts(self) -> bool:
        return bool(self.model) and any(c != 0.0 for c in self.D)

    def array(self) -> np.ndarray:
        return np.asarray(self.D, float)


PINHOLE = Lens()


def lens_from_info(model: str, d: object, where: str) -> Lens:
    """The lens of a CameraInfo's distortion_model and d (one line naming `where` for a model or coefficient count
    adlpipe cannot project with). An empty model or all-zero d is the pinhole."""
    model = str(model or "").strip()
    coeffs = [float(c) for c in np.asarray(d if d is not None else [], float).reshape(-1)]
    if not model or not any(coeffs):
        return PINHOLE
    if model not in COEFFICIENTS:
        raise AdlError(f"{where}: distortion_model {model!r} is not one adlpipe projects with "
                       f"({', '.join(COEFFICIENTS)}); rectify the images first")
    need = COEFFICIENTS[model]
    if model == "plumb_bob" and len(coeffs) in (4, 8, 12, 14):  # OpenCV accepts these lengths too
        need = len(coeffs)
    if len(coeffs) < need or (model != "plumb_bob" and len(coeffs) > need and any(coeffs[need:])):
        raise AdlError(f"{where}: distortion_model {model} needs {COEFFICIENTS[model]} coefficients in d, got "
                       f"{len(coeffs)}")
    if not np.isfinite(coeffs).all():
        raise AdlError(f"{where}: distortion coefficients are not finite")
    return Lens(model, tuple(coeffs[:need]))


def project(points: np.ndarray, K: np.ndarray, T_base_camera: np.ndarray, lens: Lens = PINHOLE,
            size: tuple[int, int] | None = None) -> np.ndarray:
    """Pixel coordinates (u, v) where base-frame points appear in the image of a camera at T_base_camera (ROS optical
    frame) with intrinsics K and `lens`. size (width, height): the lens model holds only over the image it was
    calibrated on (outside, its polynomial folds back and grows without bound), so a point keeps its pinhole
    projection unless the lens still maps outward monotonically there and its distorted or its pinhole projection
    lies in the image (a barrel lens shows at its edges points whose pinhole projection lies outside)."""
    pc = in_camera(points, T_base_camera)
    uv = pinhole(pc, K)
    if not lens.distorts:
        return uv
    front = pc[:, 2] > 0
    if not front.any():
        return uv
    out = distort(pc[front], K, lens)
    if size is None:
        uv[front] = out
        return uv
    inside = (_in_image(out, size) | _in_image(uv[front], size)) & (
        maps_outward(pc[front], K, lens, out) | (np.linalg.norm(pc[front][:, :2], axis=1) < 1e-9))
    idx = np.flatnonzero(front)[inside]
    uv[idx] = out[inside]
    return uv


def maps_outward(pc: np.ndarray, K: np.ndarray, lens: Lens, distorted: np.ndarray) -> np.ndarray:
    """Per camera-frame point, whether the lens still maps outward there: the point 1 % further out in normalised
    coordinates lands further from the principal point than `distorted` (its own distorted pixel); where not, the
    polynomial has folded back and the distorted pixel is not where the point appears."""
    centre = np.asarray(K, float)[:2, 2]
    wider = distort(np.asarray(pc, float) * np.array([1.01, 1.01, 1.0]), K, lens)
    return np.linalg.norm(wider - centre, axis=1) > np.linalg.norm(distorted - centre, axis=1)


def _in_image(uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return (uv[:, 0] >= -0.5) & (uv[:, 0] <= size[0] - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= size[1] - 0.5)


def distort(pc: np.ndarray, K: np.ndarray, lens: Lens) -> np.ndarray:
    """OpenCV's projection of camera-frame points through the lens."""
    zero = np.zeros(3)
    if lens.model == "equidistant":
        out, _ = cv2.fisheye.projectPoints(pc[:, None, :], zero, zero, np.asarray(K, float), lens.array())
    else:
        out, _ = cv2.projectPoints(pc, zero, zero, np.asarray(K, float), lens.array())
    return out.reshape(-1, 2)


def read_lens(g: object) -> Lens:
    """The lens stored beside an episode's K (datasets ingested before distortion was kept: the pinhole)."""
    attrs = getattr(g, "attrs", {})
    model = str(attrs.get("distortion_model", ""))
    return Lens(model, tuple(float(c) for c in g["D"][()])) if model and "D" in g else PINHOLE
