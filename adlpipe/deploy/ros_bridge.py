"""The ROS-free core of a robot's policy node (examples/ros2_policy_node.py wires it to rclpy): the latest messages
of the topics a lab's bags already use, by the same topic map as `ingest --config`, turned into plan requests for
`adlpipe serve`, and its replies into the waypoints a node publishes. Torch-free.

    bridge = PlanBridge(TopicMap.load("topics.yaml"), client.policy)
    bridge.on_message(topic, t, msg)       # every subscribed message (rclpy's or rosbags' objects: the same fields)
    request = bridge.request()             # None until the policy's inputs have all arrived
    plan = client.plan(**request)          # through the server
    waypoints, stamps = bridge.path(plan)  # (Tp, 3) in base_frame, absolute times (s) for a nav_msgs/Path
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from ..bags.images import decode_depth, decode_image, decode_raw
from ..bags.topics import TopicMap


def stamp_of(msg: Any, t: float) -> float:
    """The header stamp in seconds (ROS 1 secs/nsecs, ROS 2 sec/nanosec), else the receive time t."""
    st = getattr(getattr(msg, "header", None), "stamp", None)
    if st is None:
        return t
    sec = getattr(st, "sec", getattr(st, "secs", 0))
    nsec = getattr(st, "nanosec", getattr(st, "nsecs", 0))
    return float(sec) + 1e-9 * float(nsec)


class PlanBridge:
    def __init__(self, topics: TopicMap, policy: dict) -> None:
        """topics: the robot's topic map; policy: the server's spec (PolicyClient.policy)."""
        self.topics, self.policy = topics, policy
        self.n_obs = int(policy["n_obs"])
        self.frames: deque[tuple[float, np.ndarray, np.ndarray | None, np.ndarray | None]] = deque(maxlen=self.n_obs)
        self.depth: np.ndarray | None = None
        self.affordance: np.ndarray | None = None
        self.task = ""
        self.tcp: np.ndarray | None = None
        self.gripper = 0.0
        self.command: np.ndarray | None = None
        self.plan_stamp = 0.0

    def on_message(self, topic: str, t: float, msg: Any) -> None:
        """Keep what a plan needs; a camera frame takes the newest depth, tcp and gripper with it."""
        tm = self.topics
        if topic == tm.image:
            rgb = decode_image(msg, topic)
            state = None if self.tcp is None else np.append(self.tcp, self.gripper)
            self.frames.append((stamp_of(msg, t), rgb, self.depth, state))
        elif topic == tm.depth:
            self.depth = decode_depth(msg, topic)
        elif topic == tm.affordance:
            self.affordance = np.asarray(decode_raw(msg, topic), np.float32)  # a 32FC1 map in [0, 1], as is
        elif topic == tm.task:
            self.task = str(msg.data)
        elif topic in (tm.tf, tm.tf_static):
            for tr in msg.transforms:
                if tr.header.frame_id == tm.base_frame and tr.child_frame_id == tm.ee_frame:
                    v = tr.transform.translation
                    self.tcp = np.array([v.x, v.y, v.z])
        elif topic == tm.joints and tm.gripper_joint:
            names = list(msg.name)
            if tm.gripper_joint in names:
                self.gripper = float(np.asarray(msg.position)[names.index(tm.gripper_joint)])
        elif topic == tm.action:
            self.command = np.asarray(msg.position, float)[:3].copy()

    def request(self) -> dict | None:
        """The plan request's fields (PolicyClient.plan(**request)), or None while an input is still missing."""
        p = self.policy
        if not self.frames or (p["image"] and self.affordance is None):
            return None
        frames = [self.frames[0]] * (self.n_obs - len(self.frames)) + list(self.frames)  # padded, as in training
        req: dict[str, Any] = {"task": self.task}
        if p["image"]:
            req["rgb"] = np.stack([f[1] for f in frames])
            req["affordance"] = self.affordance
            depths = [f[2] for f in frames if f[2] is not None]
            if p["depth"] and len(depths) == len(frames):
                req["depth"] = np.stack(depths).astype(np.float32)
        if p["state_dim"]:
            states = [f[3] for f in frames if f[3] is not None]
            if len(states) < len(frames):
                return None
            req["state"] = np.stack(states)[:, :p["state_dim"]]
        if p["needs_command"]:
            command = self.command if self.command is not None else self.tcp  # at rest the command is the tcp
            if command is None:
                return None
            req["command"] = command
        self.plan_stamp = frames[-1][0]
        return req

    def path(self, plan: dict) -> tuple[np.ndarray, np.ndarray]:
        """(waypoints (Tp, 3) in base_frame, their absolute times in s): the plan's times are after the
        observation the request was built from."""
        return np.asarray(plan["waypoints"], float), self.plan_stamp + np.asarray(plan["times"], float)
