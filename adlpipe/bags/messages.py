"""Builds ROS messages (as rosbags dataclasses) for the ROS1 or ROS2 type store, and serialises them."""

from __future__ import annotations

import cv2
import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF = "tf2_msgs/msg/TFMessage"
JOINT_STATE = "sensor_msgs/msg/JointState"
STRING = "std_msgs/msg/String"
BOOL = "std_msgs/msg/Bool"
PATH = "nav_msgs/msg/Path"  # a policy's plan: each waypoint a pose stamped with the time it is for


def typestore(ros_version: int):  # noqa: ANN201 - rosbags Typestore
    """The ROS1 (noetic) or ROS2 (humble) type store; ROS1's lacks tf2_msgs/TFMessage, so it is added."""
    store = get_typestore(Stores.ROS1_NOETIC if ros_version == 1 else Stores.ROS2_HUMBLE)
    if TF not in store.types:
        store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF))
    return store


class MessageFactory:
    """Message construction that hides the ROS1/ROS2 field differences (Header.seq, CameraInfo K/k, ...)."""

    def __init__(self, ros_version: int) -> None:
        self.ros1 = ros_version == 1
        self.store = typestore(ros_version)
        self.T = self.store.types
        self._seq = 0

    def serialize(self, msg: object, msgtype: str) -> bytes:
        if self.ros1:
            return bytes(self.store.serialize_ros1(msg, msgtype))
        return bytes(self.store.serialize_cdr(msg, msgtype))

    def msgdef(self, msgtype: str) -> str:
        return self.store.generate_msgdef(msgtype, ros_version=1 if self.ros1 else 2)[0]

    def stamp(self, t_ns: int) -> object:
        return self.T["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000), nanosec=int(t_ns % 1_000_000_000))

    def header(self, t_ns: int, frame: str) -> object:
        H = self.T["std_msgs/msg/Header"]
        if self.ros1:
            self._seq += 1
            return H(seq=self._seq, stamp=self.stamp(t_ns), frame_id=frame)
        return H(stamp=self.stamp(t_ns), frame_id=frame)

    def image(self, t_ns: int, frame: str, array: np.ndarray, encoding: str) -> object:
        array = np.ascontiguousarray(array)
        h, w = array.shape[:2]
        return self.T[IMAGE](
            header=self.header(t_ns, frame), height=h, width=w, encoding=encoding, is_bigendian=0,
            step=int(array.strides[0]), data=np.frombuffer(array.tobytes(), np.uint8),
        )

    def compressed(self, t_ns: int, frame: str, rgb: np.ndarray, fmt: str) -> object:
        ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        assert ok
        return self.T[COMPRESSED](header=self.header(t_ns, frame), format=fmt,
                                  data=np.frombuffer(buf.tobytes(), np.uint8))

    def camera_info(self, t_ns: int, frame: str, K: np.ndarray, width: int, height: int,
                    distortion_model: str = "plumb_bob", D: np.ndarray | None = None) -> object:
        P = np.zeros((3, 4))
        P[:, :3] = K
        D = np.zeros(5) if D is None else np.asarray(D, float)
        fields = {"D": D, "K": K.reshape(9).astype(float), "R": np.eye(3).reshape(9), "P": P.reshape(12)}
        if not self.ros1:
            fields = {k.lower(): v for k, v in fields.items()}
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.T[CAMERA_INFO](header=self.header(t_ns, frame), height=height, width=width,
                                   distortion_model=distortion_model, binning_x=0, binning_y=0, roi=roi, **fields)

    def tf(self, t_ns: int, transforms: list[tuple[str, str, np.ndarray, np.ndarray]]) -> object:
        """transforms: (parent, child, translation xyz, quaternion wxyz)."""
        V, Q = self.T["geometry_msgs/msg/Vector3"], self.T["geometry_msgs/msg/Quaternion"]
        out = []
        for parent, child, p, q in transforms:
            tr = self.T["geometry_msgs/msg/Transform"](
                translation=V(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                rotation=Q(x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])),
            )
            out.append(self.T["geometry_msgs/msg/TransformStamped"](
                header=self.header(t_ns, parent), child_frame_id=child, transform=tr))
        return self.T[TF](transforms=out)

    def joint_state(self, t_ns: int, names: list[str], pos: np.ndarray, vel: np.ndarray) -> object:
        return self.T[JOINT_STATE](header=self.header(t_ns, ""), name=list(names), position=pos.astype(float),
                                   velocity=vel.astype(float), effort=np.zeros(len(names)))

    def string(self, text: str) -> object:
        return self.T[STRING](data=text)

    def boolean(self, value: bool) -> object:
        return self.T[BOOL](data=bool(value))

    def path(self, t_ns: int, frame: str, waypoints: np.ndarray, stamps_ns: list[int]) -> object:
        """nav_msgs/Path: (N, 3) positions, each PoseStamped at its own time (orientation identity)."""
        P, Pt, Q = (self.T["geometry_msgs/msg/Pose"], self.T["geometry_msgs/msg/Point"],
                    self.T["geometry_msgs/msg/Quaternion"])
        poses = [self.T["geometry_msgs/msg/PoseStamped"](
            header=self.header(tn, frame), pose=P(position=Pt(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                                                  orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0)))
            for p, tn in zip(waypoints, stamps_ns, strict=True)]
        return self.T[PATH](header=self.header(t_ns, frame), poses=poses)
