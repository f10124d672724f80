"""Rigid transforms, a small TF buffer, trajectory resampling and pinhole projection."""

from __future__ import annotations

import bisect

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """wxyz quaternion -> 3x3 rotation matrix."""
    q = np.asarray(q, float)
    n = float(np.sqrt(np.sum(q * q))) if np.isfinite(q).all() and np.abs(q).max() < 1e6 else float("nan")
    w, x, y, z = q / max(n, 1e-12) if np.isfinite(n) else (np.nan,) * 4
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """3x3 rotation -> wxyz quaternion (Shepperd's method)."""
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    return np.asarray(q)


def pose_matrix(pos: np.ndarray, quat_wxyz: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(quat_wxyz)
    T[:3, 3] = pos
    return T


class TfBuffer:
    """parent->child transforms over time (static ones hold always); lookups compose the chain to a root frame."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self.static: dict[str, np.ndarray] = {}
        self.times: dict[str, list[float]] = {}
        self.poses: dict[str, list[np.ndarray]] = {}

    def add(self, parent: str, child: str, t: float, T: np.ndarray, static: bool) -> None:
        self.parent[child] = parent
        if static:
            self.static[child] = T
            return
        ts = self.times.setdefault(child, [])
        if ts and t < ts[-1]:  # out-of-order stamps: keep the list sorted
            i = bisect.bisect_right(ts, t)
            ts.insert(i, t)
            self.poses[child].insert(i, T)
        else:
            ts.append(t)
            self.poses.setdefault(child, []).append(T)

    def _at(self, child: str, t: float, interpolate: bool = False) -> np.ndarray:
        if child in self.static:
            return self.static[child]
        ts, ps = self.times[child], self.poses[child]
        i = bisect.bisect_right(ts, t) - 1
        if not interpolate or i < 0 or i + 1 >= len(ts) or ts[i + 1] <= ts[i]:
            return ps[max(i, 0)]
        # between two samples, as tf2 does: translation linear, rotation by slerp
        w = (t - ts[i]) / (ts[i + 1] - ts[i])
        a, b = ps[i], ps[i + 1]
        T = np.eye(4)
        T[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix([a[:3, :3], b[:3, :3]]))(w).as_matrix()
        T[:3, 3] = (1 - w) * a[:3, 3] + w * b[:3, 3]
        return T

    def _ancestors(self, frame: str, t: float, interpolate: bool = False) -> dict[str, np.ndarray]:
        """Pose of `frame` in itself and in each of its ancestors up to its root, at time t."""
        out, T = {frame: np.eye(4)}, np.eye(4)
        for _ in range(64):
            if frame not in self.parent:
                break
            T = self._at(frame, t, interpolate) @ T
            frame = self.parent[frame]
            if frame in out:  # a cycle in a broken tree
                break
            out[frame] = T
        return out

    def lookup(self, target: str, source: str, t: float, interpolate: bool = False) -> np.ndarray | None:
        """Pose of `source` in `target` at time t (latest sample at or before t; with `interpolate`, between the
        samples around t, as tf2 does: a moving camera between its arm's tf messages), or None if not connected.
        Any two frames of one tree are connected through their lowest common ancestor (a camera and a robot base
        both below world, map or odom): up from the source, up from the target, and across."""
        up = self._ancestors(source, t, interpolate)
        T_target, frame = np.eye(4), target  # the target's pose in `frame`
        for _ in range(64):
            if frame in up:
                return np.linalg.inv(T_target) @ up[frame]
            if frame not in self.parent:
                return None
            T_target = self._at(frame, t, interpolate) @ T_target
            frame = self.parent[frame]
        return None

    def motion_times(self, frame: str, root: str) -> tuple[str, list[float]] | None:
        """The frame whose samples time `frame`'s path in `root`: `frame` itself if it moves, else its nearest
        moving ancestor (a tool frame that robot_state_publisher puts on /tf_static, off a moving link), with the
        sample times. None if no frame on the chain to `root` moves."""
        for _ in range(64):
            if self.times.get(frame):
                return frame, self.times[frame]
            if frame == root or frame not in self.parent:
                return None
            frame = self.parent[frame]
        return None

    def first_time(self, child: str) -> float | None:
        return self.times[child][0] if self.times.get(child) else None


def path_at(t: np.ndarray | float, times: np.ndarray, values: np.ndarray) -> np.ndarray:
    """A sampled path (times (M,), values (M, D)) at the time(s) t, linearly interpolated per dimension and held
    at its ends: shape t.shape + (D,)."""
    return np.stack([np.interp(t, times, values[:, k]) for k in range(values.shape[1])], axis=-1)


def resample(times: np.ndarray, values: np.ndarray, t_start: float, t_end: float, n: int) -> np.ndarray:
    """n samples evenly spaced in time over [t_start, t_end], linearly interpolated per dimension."""
    return path_at(np.linspace(t_start, t_end, n), times, values)


def in_camera(points: np.ndarray, T_base_camera: np.ndarray) -> np.ndarray:
    """Base-frame points (N, 3) in the frame of a camera at T_base_camera (ROS optical frame)."""
    T = np.linalg.inv(T_base_camera)
    return np.asarray(points, float).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]


def pinhole(pc: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates (u, v) of camera-frame points through the undistorted intrinsics K."""
    uv = pc @ np.asarray(K, float).T
    return uv[:, :2] / uv[:, 2:3]


def project(points: np.ndarray, K: np.ndarray, T_base_camera: np.ndarray) -> np.ndarray:
    """Pixel coordinates (u, v) of base-frame points seen by a pinhole camera at T_base_camera (ROS optical frame);
    a camera with a lens: adlpipe.geometry.camera.project."""
    return pinhole(in_camera(points, T_base_camera), K)


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics of an image resized by (sx, sy), pixel centres at integer coordinates."""
    K2 = K.copy()
    K2[0, 0] *= sx
    K2[1, 1] *= sy
    K2[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K2[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K2
