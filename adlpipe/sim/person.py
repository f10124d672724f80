"""The person who moves (record / replay --moving-person): once during the episode the manikin's head turns and nods
and its left forearm lifts, each with a minimum-jerk profile, at the pace of a seated person.

Amplitudes and speeds. The head turns by 10-20 degrees and nods by 5-12 degrees, each over 1.0-1.6 s; the forearm
lifts by 8-15 degrees about the elbow (its hand end rises 3-5 cm) over 1.0-1.6 s. A minimum-jerk move peaks at
1.875 x its mean speed: at most about 38 degrees/s for the head and 28 degrees/s for the forearm. These are
deliberately the slow, comfortable movements of a seated person who shifts while being assisted: well inside the
active ranges of motion of the cervical spine (about +-70 degrees of rotation and 50-60 degrees of flexion and of
extension; Ferrario et al., 2002, "Active range of motion of the head and cervical spine", J Orthop Res 20(1)), and
a fraction of the peak angular velocities of fast voluntary head rotations (several hundred degrees/s; Roijezon et
al., 2010, "Kinematics of fast cervical rotations in persons with chronic neck pain", J NeuroEng Rehabil 7:52).
Assistive Gym's "active human" (Erickson et al., ICRA 2020) moves a simulated person's head and arms during
assistance in the same spirit.

Each move starts at a seeded time between 0.3 s and 1.5 s (the episodes last 2.3-5.5 s) and holds its end pose:
in the short tasks (wipe the nose, brush the teeth) the person is still moving when the tool touches them, in the
long ones (feed, put on the hat) they have moved before the robot arrives. The moving parts are MuJoCo mocap bodies
(`manikin_head`, `manikin_forearm`) carrying the same geoms and sites as the still manikin, so that the task
predicates, the demonstrator's keypoints and the contact force on the person follow them; the scene of a still
person is built exactly as before (no mocap bodies).
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

# Pivots in the manikin's frame: the top of the neck (the head turns and nods about it) and the left elbow (the
# forearm lifts about the horizontal axis across it).
NECK = np.array([0.0, 0.12, 0.29])
ELBOW = np.array([-0.22, 0.05, 0.06])
HAND = np.array([-0.12, -0.12, 0.035])
HEAD_BODY, FOREARM_BODY = "manikin_head", "manikin_forearm"
KEYS = ("head_t0", "head_s", "head_yaw", "head_pitch", "arm_t0", "arm_s", "arm_lift")


def draw_motion(rng: np.random.Generator) -> dict[str, float]:
    """A seeded motion (angles in radians, times in seconds from the episode's start)."""
    sign = rng.choice([-1.0, 1.0], size=2)
    return {"head_t0": float(rng.uniform(0.3, 1.5)), "head_s": float(rng.uniform(1.0, 1.6)),
            "head_yaw": float(sign[0] * np.deg2rad(rng.uniform(10, 20))),
            "head_pitch": float(sign[1] * np.deg2rad(rng.uniform(5, 12))),
            "arm_t0": float(rng.uniform(0.3, 1.5)), "arm_s": float(rng.uniform(1.0, 1.6)),
            "arm_lift": float(np.deg2rad(rng.uniform(8, 15)))}


def _progress(t: float, t0: float, seconds: float) -> float:
    """Minimum-jerk progress 0..1 of a move that starts at t0 and lasts `seconds`."""
    s = float(np.clip((t - t0) / seconds, 0.0, 1.0))
    return 10 * s**3 - 15 * s**4 + 6 * s**5


def _quat(axis: np.ndarray, angle: float) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_axisAngle2Quat(q, np.asarray(axis, float), float(angle))
    return q


def _mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mulQuat(q, a, b)
    return q


def forearm_axis() -> np.ndarray:
    """The horizontal axis across the forearm at the elbow: a positive turn about it lifts the hand."""
    axis = np.cross(HAND - ELBOW, [0.0, 0.0, 1.0])
    return axis / np.linalg.norm(axis)


def local_rotations(person: dict[str, float], t: float) -> tuple[np.ndarray, np.ndarray]:
    """(head, forearm) orientations in the manikin's frame at time t, as wxyz quaternions."""
    h = _progress(t, person["head_t0"], person["head_s"])
    a = _progress(t, person["arm_t0"], person["arm_s"])
    head = _mul(_quat([0, 0, 1], h * person["head_yaw"]), _quat([1, 0, 0], h * person["head_pitch"]))
    return head, _quat(forearm_axis(), a * person["arm_lift"])


def pivot_in_base(manikin: tuple[float, float, float, float], pivot: np.ndarray) -> np.ndarray:
    """Where a pivot given in the manikin's frame lies in base_link, the manikin at (x, y, z, yaw)."""
    x, y, z, yaw = manikin
    w = np.zeros(3)
    mujoco.mju_rotVecQuat(w, np.asarray(pivot, float), _quat([0, 0, 1], yaw))
    return w + [x, y, z]


def mover(model: mujoco.MjModel, spec) -> Callable[[mujoco.MjData, float], None]:  # noqa: ANN001 - a SceneSpec
    """fn(data, t): put the head and forearm mocap bodies where the person of `spec` has them at time t."""
    manikin, person = spec.poses["manikin"], spec.person
    base_q = _quat([0, 0, 1], manikin[3])
    ids = [model.body_mocapid[model.body(n).id] for n in (HEAD_BODY, FOREARM_BODY)]
    pivots = [pivot_in_base(manikin, p) for p in (NECK, ELBOW)]

    def move(data: mujoco.MjData, t: float) -> None:
        for mid, pivot, q in zip(ids, pivots, local_rotations(person, t), strict=True):
            data.mocap_pos[mid] = pivot
            data.mocap_quat[mid] = _mul(base_q, q)

    return move


def still_until(person: dict[str, float]) -> float:
    """When the person starts to move (s)."""
    return min(person["head_t0"], person["arm_t0"])


def moved_by(person: dict[str, float]) -> float:
    """When the person has stopped moving (s)."""
    return max(person["head_t0"] + person["head_s"], person["arm_t0"] + person["arm_s"])
