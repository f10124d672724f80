"""A ROS 2 node that runs a served policy on a robot: it subscribes to the topics a lab's bags already use (the same
topic map as `adlpipe ingest --config`), asks `adlpipe serve` for a plan at each camera frame, and publishes the plan
as a nav_msgs/Path on /adl/plan and the policy's name on /adl/policy.

    adlpipe serve pipelines/closed_loop/models/fm_cnn --host 0.0.0.0 --token-file token.txt      # the GPU box
    python examples/ros2_policy_node.py ws://gpu-box:8765 --config topics.yaml --token-file token.txt   # the robot

Needs rclpy (a ROS 2 install, not on the package index) and, from adlpipe, only the torch-free parts: the client and
adlpipe.deploy.ros_bridge, the node's ROS-free core, which the tests feed a real bag's messages. A lab's arm
controller follows /adl/plan (each pose stamped with the time it is for). Record the trial with
`ros2 bag record` of the camera, tf, joints, /adl/plan and /adl/policy, and publish the outcome on /adl/outcome
(std_msgs/String JSON, e.g. {"policy": "fm_cnn", "success": true, "force_n": 4.2}) when the trial ends:
`adlpipe trials` decides from those bags, and `adlpipe ingest` keeps them as data.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import rclpy  # type: ignore[import-not-found]
from builtin_interfaces.msg import Time  # type: ignore[import-not-found]
from geometry_msgs.msg import PoseStamped  # type: ignore[import-not-found]
from nav_msgs.msg import Path as PathMsg  # type: ignore[import-not-found]
from rclpy.node import Node  # type: ignore[import-not-found]
from sensor_msgs.msg import CompressedImage, Image, JointState  # type: ignore[import-not-found]
from std_msgs.msg import String  # type: ignore[import-not-found]
from tf2_msgs.msg import TFMessage  # type: ignore[import-not-found]

from adlpipe.bags.topics import TopicMap
from adlpipe.deploy.client import PolicyClient
from adlpipe.deploy.ros_bridge import PlanBridge


class PolicyNode(Node):
    def __init__(self, client: PolicyClient, topics: TopicMap, compressed: bool) -> None:
        super().__init__("adlpipe_policy")
        self.client, self.topics = client, topics
        self.bridge = PlanBridge(topics, client.policy)
        self.plan_pub = self.create_publisher(PathMsg, "/adl/plan", 10)
        self.policy_pub = self.create_publisher(String, "/adl/policy", 10)
        subs = [(topics.image, CompressedImage if compressed else Image), (topics.depth, Image),
                (topics.affordance, Image), (topics.task, String), (topics.tf, TFMessage),
                (topics.tf_static, TFMessage), (topics.joints, JointState), (topics.action, JointState)]
        for topic, kind in subs:
            if topic:
                self.create_subscription(kind, topic, lambda msg, t=topic: self.on_message(t, msg), 10)

    def on_message(self, topic: str, msg: object) -> None:
        now = self.get_clock().now().nanoseconds / 1e9
        self.bridge.on_message(topic, now, msg)
        if topic != self.topics.image:
            return
        request = self.bridge.request()
        if request is None:
            return
        waypoints, stamps = self.bridge.path(self.client.plan(**request))  # blocks: one plan per frame at most
        out = PathMsg()
        out.header.frame_id = self.topics.base_frame
        out.header.stamp = self.get_clock().now().to_msg()
        for w, s in zip(waypoints, stamps, strict=True):
            pose = PoseStamped()
            pose.header.frame_id = self.topics.base_frame
            pose.header.stamp = Time(sec=int(s), nanosec=int((s % 1) * 1e9))
            pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = map(float, w)
            pose.pose.orientation.w = 1.0
            out.poses.append(pose)
        self.plan_pub.publish(out)
        self.policy_pub.publish(String(data=str(self.client.policy["model"])))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("url")
    p.add_argument("--config", help="the topic map (ingest --config); default: the ADL world's topics")
    p.add_argument("--token-file", type=Path)
    p.add_argument("--compressed", action="store_true", help="the camera publishes sensor_msgs/CompressedImage")
    args = p.parse_args()
    token = args.token_file.read_text().strip() if args.token_file else None
    rclpy.init()
    with PolicyClient(args.url, token=token) as client:
        node = PolicyNode(client, TopicMap.load(args.config), args.compressed)
        try:
            rclpy.spin(node)
        finally:
            node.destroy_node()
            rclpy.shutdown()


if __name__ == "__main__":
    main()
