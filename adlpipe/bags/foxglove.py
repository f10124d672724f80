"""MCAP written without ROS by the Foxglove SDK: the well-known foxglove schemas, in protobuf (decoded by
mcap-protobuf-support from the schema the file carries) or JSON, read as the ROS messages they stand for, so the
same topic map reads them (issue E.4):

    foxglove.RawImage          -> sensor_msgs/msg/Image           (timestamp, frame_id, width, height, encoding,
                                                                   step, data)
    foxglove.CompressedImage   -> sensor_msgs/msg/CompressedImage (format, data)
    foxglove.CameraCalibration -> sensor_msgs/msg/CameraInfo      (width, height, distortion_model, D, K, R, P)
    foxglove.FrameTransforms   -> tf2_msgs/msg/TFMessage          (transforms: parent_frame_id, child_frame_id,
                                                                   translation, rotation)
    foxglove.FrameTransform    -> tf2_msgs/msg/TFMessage          (one transform)
"""

from __future__ import annotations

import base64
import json
from types import SimpleNamespace as NS

AS_ROS = {"foxglove.RawImage": "sensor_msgs/msg/Image", "foxglove.CompressedImage": "sensor_msgs/msg/CompressedImage",
          "foxglove.CameraCalibration": "sensor_msgs/msg/CameraInfo",
          "foxglove.FrameTransforms": "tf2_msgs/msg/TFMessage", "foxglove.FrameTransform": "tf2_msgs/msg/TFMessage"}


def _get(msg: object, name: str, default: object = None) -> object:
    return msg.get(name, default) if isinstance(msg, dict) else getattr(msg, name, default)


def _stamp(ts: object) -> NS:
    """A protobuf Timestamp (seconds, nanos) or the JSON form ({sec, nsec}) as ROS 2's (sec, nanosec)."""
    if ts is None:
        return NS(sec=0, nanosec=0)
    sec = _get(ts, "seconds", _get(ts, "sec", 0))
    nsec = _get(ts, "nanos", _get(ts, "nsec", 0))
    return NS(sec=int(sec or 0), nanosec=int(nsec or 0))


def _bytes(data: object) -> bytes:
    return base64.b64decode(data) if isinstance(data, str) else bytes(data)  # JSON carries bytes as base64


def _header(msg: object, frame: str = "frame_id") -> NS:
    return NS(stamp=_stamp(_get(msg, "timestamp")), frame_id=str(_get(msg, frame, "")))


def _transform(t: object) -> NS:
    tr, rot = _get(t, "translation"), _get(t, "rotation")
    return NS(header=_header(t, "parent_frame_id"), child_frame_id=str(_get(t, "child_frame_id", "")),
              transform=NS(translation=NS(x=_get(tr, "x", 0.0), y=_get(tr, "y", 0.0), z=_get(tr, "z", 0.0)),
                           rotation=NS(x=_get(rot, "x", 0.0), y=_get(rot, "y", 0.0), z=_get(rot, "z", 0.0),
                                       w=_get(rot, "w", 1.0))))


def as_ros(schema: str, msg: object) -> object:
    """The foxglove message (protobuf object or JSON dict) as the ROS message it stands for."""
    if schema == "foxglove.RawImage":
        return NS(header=_header(msg), height=int(_get(msg, "height")), width=int(_get(msg, "width")),
                  encoding=str(_get(msg, "encoding")), is_bigendian=0, step=int(_get(msg, "step")),
                  data=_bytes(_get(msg, "data", b"")))
    if schema == "foxglove.CompressedImage":
        return NS(header=_header(msg), format=str(_get(msg, "format")), data=_bytes(_get(msg, "data", b"")))
    if schema == "foxglove.CameraCalibration":
        return NS(header=_header(msg), height=int(_get(msg, "height")), width=int(_get(msg, "width")),
                  distortion_model=str(_get(msg, "distortion_model", "")), d=list(_get(msg, "D", [])),
                  k=list(_get(msg, "K", [])), r=list(_get(msg, "R", [])), p=list(_get(msg, "P", [])))
    if schema == "foxglove.FrameTransforms":
        return NS(transforms=[_transform(t) for t in _get(msg, "transforms", [])])
    if schema == "foxglove.FrameTransform":
        return NS(transforms=[_transform(msg)])
    return msg


class JsonDecoderFactory:
    """mcap's decoder-factory interface for JSON-encoded channels (the Foxglove SDK's other encoding)."""

    def decoder_for(self, message_encoding: str, schema: object) -> object:
        if message_encoding != "json":
            return None
        return lambda data: json.loads(bytes(data))


class SafeFactory:
    """A decoder factory whose schema parser may fail on a schema it cannot read (mcap-protobuf-support on a
    FileDescriptorSet that is not one): then it has no decoder for the channel, which reader.NoDecoder names."""

    def __init__(self, factory: object) -> None:
        self.factory = factory

    def decoder_for(self, message_encoding: str, schema: object) -> object:
        try:
            return self.factory.decoder_for(message_encoding, schema)
        except Exception:  # noqa: BLE001 - whatever the parser raises, the channel is one it cannot decode
            return None
