"""MCAP written without ROS by the Foxglove SDK (issue E.4): foxglove.RawImage, CameraCalibration and
FrameTransforms, in protobuf (written with mcap-protobuf-support's writer and foxglove-schemas-protobuf, the classes
the SDK uses) and in JSON (mcap's writer with the schemas' JSON form), read through the same topic map."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import yaml
from layouts import smooth_rgb

from adlpipe.bags.topics import TopicMap
from adlpipe.dataset import schema
from adlpipe.ingest import ingest

T0 = 1_767_225_600 * 10**9
W, H, HZ = 64, 48, 10
K = [50.0, 0.0, 31.5, 0.0, 50.0, 23.5, 0.0, 0.0, 1.0]
CAMERA = ([0.9, -0.5, 0.9], [0.0, 0.0, 0.0, 1.0])  # base_link -> camera (x, y, z; qx, qy, qz, qw)


def ee_at(t: float) -> list[float]:
    return [0.4 + 0.1 * np.cos(t), 0.1 * np.sin(t), 0.3 + 0.05 * t]


def messages() -> list[tuple[int, str, str, dict]]:
    """(log time, topic, schema, fields) of a 3 s demonstration, in the foxglove schemas' field names."""
    out = [(T0, "/tf_static", "foxglove.FrameTransforms", {"transforms": [
        {"timestamp": (T0, ), "parent_frame_id": "base_link", "child_frame_id": "camera",
         "translation": dict(zip("xyz", CAMERA[0], strict=True)),
         "rotation": dict(zip("xyzw", CAMERA[1], strict=True))}]})]
    for k in range(3 * 50 + 1):
        tn = T0 + k * 20_000_000
        out.append((tn, "/tf", "foxglove.FrameTransforms", {"transforms": [
            {"timestamp": (tn, ), "parent_frame_id": "base_link", "child_frame_id": "ee",
             "translation": dict(zip("xyz", ee_at(k / 50), strict=True)),
             "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}]}))
    for k in range(3 * HZ + 1):
        tn = T0 + k * 100_000_000
        out.append((tn, "/camera/calibration", "foxglove.CameraCalibration",
                    {"timestamp": (tn, ), "frame_id": "camera", "width": W, "height": H, "distortion_model": "",
                     "D": [], "K": K, "R": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], "P": K[:3] + [0.0] + K[3:6] + [0.0]
                     + K[6:] + [0.0]}))
        out.append((tn, "/camera/image", "foxglove.RawImage",
                    {"timestamp": (tn, ), "frame_id": "camera", "width": W, "height": H, "encoding": "rgb8",
                     "step": 3 * W, "data": smooth_rgb(k, H, W).tobytes()}))
    return sorted(out, key=lambda m: m[0])


def write_protobuf(path: Path) -> None:
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
    from google.protobuf.timestamp_pb2 import Timestamp
    from mcap_protobuf.writer import Writer

    classes = {"foxglove.RawImage": RawImage, "foxglove.CameraCalibration": CameraCalibration,
               "foxglove.FrameTransforms": FrameTransforms}

    def stamp(fields: dict) -> dict:
        return {k: (Timestamp(seconds=v[0] // 10**9, nanos=v[0] % 10**9) if k == "timestamp" else
                    [stamp(t) for t in v] if k == "transforms" else v) for k, v in fields.items()}

    with open(path, "wb") as f, Writer(f) as w:
        for tn, topic, name, fields in messages():
            w.write_message(topic, classes[name](**stamp(fields)), log_time=tn, publish_time=tn)


def write_json(path: Path) -> None:
    from mcap.writer import Writer

    def plain(v: object) -> object:
        if isinstance(v, dict):
            return {k: ({"sec": x[0] // 10**9, "nsec": x[0] % 10**9} if k == "timestamp" else
                        base64.b64encode(x).decode() if k == "data" else plain(x)) for k, x in v.items()}
        return [plain(x) for x in v] if isinstance(v, list) else v

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="foxglove-sdk-like")
        channels: dict[str, int] = {}
        for tn, topic, name, fields in messages():
            if topic not in channels:
                sid = w.register_schema(name=name, encoding="jsonschema", data=json.dumps({"type": "object"}).encode())
                channels[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
            w.add_message(channels[topic], log_time=tn, publish_time=tn, data=json.dumps(plain(fields)).encode())
        w.finish()


@pytest.mark.parametrize("encoding", ["protobuf", "json"])
def test_foxglove_schemas_are_read_as_the_ros_messages_they_stand_for(tmp_path: Path, encoding: str) -> None:
    bag = tmp_path / "sdk.mcap"
    (write_protobuf if encoding == "protobuf" else write_json)(bag)
    cfg = tmp_path / "map.yaml"
    cfg.write_text(yaml.safe_dump(dict(image="/camera/image", camera_info="/camera/calibration", depth=None,
                                       affordance=None, joints=None, task=None, tf="/tf", tf_static="/tf_static",
                                       base_frame="base_link", ee_frame="ee", gripper_joint=None)))
    out = tmp_path / "x.h5"
    assert ingest([bag], out, TopicMap.load(cfg), n_waypoints=32, size=48, task="wipe the table")["new"] == 1
    with h5py.File(out) as f:
        ep = schema.read_episode(f, schema.episode_names(f)[0])
    with schema.open_dataset(out) as f:
        g = f[schema.EPISODES][schema.episode_names(f)[0]]
        t, rgb = g["frames/t"][()], g["frames/rgb"][()]
    assert len(t) == 3 * HZ + 1 and t == pytest.approx(np.arange(3 * HZ + 1) / HZ, abs=1e-6)
    tq = np.linspace(0, ep.duration_s, 32)
    assert np.abs(ep.traj3d - np.array([ee_at(x) for x in tq])).max() < 1e-3  # the FrameTransforms' path
    assert ep.K[0, 0] == pytest.approx(50.0 * 48 / W) and ep.K[1, 1] == pytest.approx(50.0 * 48 / H)  # K, resized
    assert np.allclose(ep.T_base_camera[:3, 3], CAMERA[0]) and ep.camera_frame == "camera"
    assert rgb.shape == (3 * HZ + 1, 48, 48, 3)
    want = cv2.resize(smooth_rgb(7, H, W), (48, 48), interpolation=cv2.INTER_AREA).astype(float)
    assert np.abs(rgb[7].astype(float) - want).mean() < 2.0  # the RawImage's pixels
