"""An episode of the ADL world (adlpipe.sim.episode.Streams, also Push-T's and Kitchen's seeded worlds, a closed-loop
trial or a labelled rollout) written as a bag with the real writer: what `adlpipe record` writes and `adlpipe ingest`
reads back, so that simulated data takes the path a robot's recording takes."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..bags import messages as M
from ..bags.topics import TopicMap
from ..bags.writer import BagWriter
from ..geometry.transforms import matrix_to_quat

BASE_TIME_NS = 1_767_225_600 * 10**9  # 2026-01-01T00:00:00Z; episode k starts k*100 s later (deterministic bags)
CAMERA_FRAME = "camera_color_optical_frame"
REFERENCE_NAMES = ["tcp_x", "tcp_y", "tcp_z"]
PLAN_TOPIC = "/adl/plan"  # a trial's plans (nav_msgs/Path per re-plan, stamped at its observation)
EXPERT_PLAN_TOPIC = "/adl/expert_plan"  # a labelled rollout's expert plans (adlpipe.sim.dagger), in the same form


def write_episode_bag(st, path: Path, fmt: str, image_format: str, depth_format: str, episode_index: int,
                      topics: TopicMap = TopicMap(),  # noqa: B008 - frozen dataclass
                      outcome: list[tuple[str, str, object]] | None = None) -> Path:
    """Write one recorded episode (adlpipe.sim.episode.Streams) as a bag; `outcome`: (topic, type, value) messages
    (std_msgs String or Bool) written after its last frame, as a trial bag carries them (adlpipe.trials)."""
    t0 = BASE_TIME_NS + episode_index * 100 * 10**9
    ns = lambda t: t0 + int(round(t * 1e9))  # noqa: E731
    w = BagWriter(path, fmt)
    f = w.msgs
    try:
        events: list[tuple[int, int, str, str, Callable[..., object]]] = []  # (t_ns, order, topic, type, builder)
        cam_q = matrix_to_quat(st.T_base_camera[:3, :3])
        statics = [(topics.base_frame, CAMERA_FRAME, st.T_base_camera[:3, 3], cam_q)]
        for name, (x, y, z, yaw) in st.spec.poses.items():
            if name == "manikin" or not any(name in o for _, o in st.objects[:1]):
                statics.append((topics.base_frame, name, np.array([x, y, z]),
                                np.array([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)])))
        events.append((ns(0), 0, topics.tf_static, M.TF, lambda: f.tf(ns(0), statics)))
        if topics.task:
            events.append((ns(0), 1, topics.task, M.STRING, lambda: f.string(st.task)))
        if topics.affordance and st.affordance is not None:
            events.append((ns(0), 2, topics.affordance, M.IMAGE,
                           lambda: f.image(ns(0), CAMERA_FRAME, st.affordance.astype(np.float32), "32FC1")))
        for t, rgb, depth in st.camera:
            tn = ns(t)
            events.append((tn, 3, topics.camera_info, M.CAMERA_INFO,
                           lambda tn=tn: f.camera_info(tn, CAMERA_FRAME, st.K, st.width, st.height)))
            if image_format == "raw":
                events.append((tn, 4, topics.image, M.IMAGE,
                               lambda tn=tn, rgb=rgb: f.image(tn, CAMERA_FRAME, rgb, "rgb8")))
            else:
                events.append((tn, 4, topics.image, M.COMPRESSED,
                               lambda tn=tn, rgb=rgb: f.compressed(tn, CAMERA_FRAME, rgb, image_format)))
            if topics.depth:
                if depth_format == "16UC1":
                    d = np.clip(np.round(np.nan_to_num(depth, nan=0.0) * 1000.0), 0, 65535).astype(np.uint16)
                else:
                    d = depth.astype(np.float32)
                events.append((tn, 5, topics.depth, M.IMAGE,
                               lambda tn=tn, d=d: f.image(tn, CAMERA_FRAME, d, depth_format)))
        for t, objs in st.objects:
            tn = ns(t)
            tfs = [(topics.base_frame, n, p, q) for n, (p, q) in objs.items()]
            if tfs:
                events.append((tn, 6, topics.tf, M.TF, lambda tn=tn, tfs=tfs: f.tf(tn, tfs)))
        for t, p, q in st.ee:
            tn = ns(t)
            events.append((tn, 7, topics.tf, M.TF,
                           lambda tn=tn, p=p, q=q: f.tf(tn, [(topics.base_frame, topics.ee_frame, p, q)])))
        extra = [(topic, names, stream) for topic, (names, stream) in st.extra_states.items()]
        if topics.reference and st.reference:  # a disturbed demonstrator's own path (record --recoveries)
            extra.append((topics.reference, REFERENCE_NAMES, st.reference))
        if topics.expert_phase and st.expert_phase:  # a labelled rollout's expert phase (adlpipe.sim.dagger)
            extra.append((topics.expert_phase, ["phase_s"], [(t, [x]) for t, x in st.expert_phase]))
        for topic, names, stream in ((topics.state, st.state_names, st.states),
                                     (topics.action, st.action_names, st.actions), *extra):
            for t, values in stream if topic else []:
                tn = ns(t)
                events.append((tn, 9, topic, M.JOINT_STATE, lambda tn=tn, v=values, n=names:
                               f.joint_state(tn, n, np.asarray(v, float), np.zeros(len(n)))))
        if topics.joints:
            for t, qp, qv in st.joints:
                tn = ns(t)
                events.append((tn, 8, topics.joints, M.JOINT_STATE,
                               lambda tn=tn, qp=qp, qv=qv: f.joint_state(tn, st.joint_names, qp, qv)))
        for topic, plans in ((PLAN_TOPIC, st.plans), (EXPERT_PLAN_TOPIC, st.expert_plans)):
            for t, waypoints, times in plans:  # a trial's plans (adlpipe.deploy.trial_bags), each at its observation
                tn = ns(t)
                stamps = [ns(t + float(x)) for x in times]
                events.append((tn, 9, topic, M.PATH, lambda tn=tn, w=waypoints, ts=stamps: f.path(
                    tn, topics.base_frame, w, ts)))
        if topics.intervention:
            for t, drives in st.interventions:  # who drove from t on (sim.dagger)
                events.append((ns(t), 9, topics.intervention, M.BOOL, lambda v=drives: f.boolean(v)))
        for topic, msgtype, value in outcome or []:  # a trial's outcome, after its last frame (frames in time order)
            events.append((ns(st.camera[-1][0] + 0.01), 10, topic, msgtype,
                           lambda v=value, b=msgtype == M.BOOL: f.boolean(v) if b else f.string(str(v))))
        events.sort(key=lambda e: (e[0], e[1]))
        w.declare_counts(Counter(topic for _, _, topic, _, _ in events))
        for tn, _, topic, msgtype, build in events:
            w.write(topic, msgtype, tn, build())
        return w.close()
    except BaseException:
        w.abort()
        raise
