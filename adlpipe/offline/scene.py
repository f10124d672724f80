"""The scene the camera saw at the first frame, as a depth image and a point cloud in the robot's base frame, and
what a replayed arm does in it: its clearance to the observed surfaces (a k-d tree over the cloud, scipy) and how
far it goes behind them (each arm point projected into the depth image through the camera model: deeper than
the surface seen along its ray means inside or behind an object).

The robot itself is in the first frame: its pixels (the arm at the recorded joint state, projected and dilated)
are left out of both, so the arm is never found colliding with its own image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..geometry.camera import PINHOLE, Lens, project
from ..geometry.transforms import in_camera

ROBOT_MASK_PX = 2  # pixels of dilation around the arm's own projection in the first frame


@dataclass
class DepthScene:
    depth: np.ndarray  # (S, S) metres along the optical axis, NaN: no return (or the robot itself)
    K: np.ndarray
    T_base_camera: np.ndarray
    lens: Lens
    points: np.ndarray  # (M, 3) the observed surfaces in the base frame
    tree: cKDTree

    @classmethod
    def from_depth(cls, depth: np.ndarray, K: np.ndarray, T_base_camera: np.ndarray, lens: Lens = PINHOLE,
                   robot_points: np.ndarray | None = None) -> DepthScene:
        """From a first-frame depth image (metres, NaN = no return); robot_points (base frame): the arm as it was
        when the image was taken, whose pixels are removed."""
        d = np.array(depth, np.float32)
        size = d.shape[::-1]
        if robot_points is not None and len(robot_points):
            mask: np.ndarray = np.zeros(d.shape, np.uint8)
            uv = np.round(project(robot_points, K, T_base_camera, lens, size)).astype(int)
            ok = (uv[:, 0] >= 0) & (uv[:, 0] < size[0]) & (uv[:, 1] >= 0) & (uv[:, 1] < size[1])
            mask[uv[ok, 1], uv[ok, 0]] = 1
            mask = cv2.dilate(mask, np.ones((2 * ROBOT_MASK_PX + 1,) * 2, np.uint8))
            d[mask > 0] = np.nan
        points = back_project(d, K, T_base_camera, lens)
        return cls(d, K, T_base_camera, lens, points, cKDTree(points if len(points) else np.zeros((1, 3)) + 1e6))

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Distance (m) from each point to the nearest observed surface point."""
        return self.tree.query(points)[0]

    def behind(self, points: np.ndarray) -> np.ndarray:
        """How far (m) each base-frame point lies behind the surface the camera saw along its ray: > 0 inside or
        behind an observed object, < 0 in front of it, NaN outside the image or where there was no return."""
        h, w = self.depth.shape
        z = in_camera(points, self.T_base_camera)[:, 2]
        uv = np.round(project(points, self.K, self.T_base_camera, self.lens, (w, h))).astype(int)
        out = np.full(len(points), np.nan)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        out[ok] = z[ok] - self.depth[uv[ok, 1], uv[ok, 0]]
        return out

    def pixels(self, points: np.ndarray) -> np.ndarray:
        """(u, v) integer pixels of base-frame points, clipped to the image."""
        h, w = self.depth.shape
        uv = np.round(project(points, self.K, self.T_base_camera, self.lens, (w, h))).astype(int)
        return np.clip(uv, 0, [w - 1, h - 1])


def back_project(depth: np.ndarray, K: np.ndarray, T_base_camera: np.ndarray, lens: Lens = PINHOLE) -> np.ndarray:
    """(M, 3) base-frame points of every pixel with a return: the pixel undistorted through the lens (OpenCV), its
    ray scaled to the depth, moved into the base frame by the camera pose."""
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    if not len(u):
        return np.zeros((0, 3))
    px = np.stack([u, v], 1).astype(np.float64)[:, None, :]
    if lens.distorts and lens.model == "equidistant":
        xy = cv2.fisheye.undistortPoints(px, np.asarray(K, float), lens.array()).reshape(-1, 2)
    elif lens.distorts:  # iterated to 1e-10: OpenCV's default five iterations leave 0.03 px at a wide lens's corners
        xy = cv2.undistortPoints(px, np.asarray(K, float), lens.array(), None, None, None,
                                 (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)).reshape(-1, 2)
    else:
        xy = (px.reshape(-1, 2) - K[:2, 2]) / np.diag(K)[:2]
    z = depth[v, u].astype(np.float64)
    pc = np.concatenate([xy * z[:, None], z[:, None]], 1)
    return pc @ T_base_camera[:3, :3].T + T_base_camera[:3, 3]
