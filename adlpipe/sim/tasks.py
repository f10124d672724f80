"""The 10 ADL tasks of the paper: scene randomisation, a scripted demonstrator and a success predicate each.

Demonstrations are multimodal where the task allows (approach left or right of an obstacle, two grasp sides,
stroke direction), so a regressor trained with MSE averages the modes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np

from .world import DUSTPAN_HALF, SceneSpec, tool_tip_offset

TASK_NAMES = [
    "sweep the trash", "pass the water", "hang the towel", "put on the hat", "cover the food",
    "wipe the nose", "wipe the forearm", "feed the human", "comb the hair", "brush the teeth",
]


class Scene:
    """Read access to a built scene: site and body positions in base_link."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, spec: SceneSpec) -> None:
        self.m, self.d, self.spec = model, data, spec

    def site(self, name: str) -> np.ndarray:
        return self.d.site_xpos[self.m.site(name).id].copy()

    def body(self, name: str) -> np.ndarray:
        return self.d.xpos[self.m.body(name).id].copy()

    def upright(self, name: str) -> float:
        """Cosine between the body's z-axis and world up."""
        return float(self.d.xmat[self.m.body(name).id].reshape(3, 3)[2, 2])

    @property
    def mode(self) -> int:
        return int(self.spec.extras.get("mode", 1))


Point = Callable[[Scene], np.ndarray]

# What success means (stated in README): a contact force on the manikin above FORCE_LIMIT_N at any time fails the
# episode; a grasp needs the tcp within GRASP_RADIUS of the grasp site (controller.py).
FORCE_LIMIT_N = 20.0
# The demonstrator aims 8 mm below a grasp site: the fingers close round the object, and the tcp passes through the
# site instead of creeping up on it (the grasp fires at the closest approach within GRASP_RADIUS).
GRASP_DEPTH = np.array([0.0, 0.0, -0.008])


@dataclass(frozen=True)
class Stroke:
    """Tool contact with the manikin, within `radius` of the segment a-b on its surface, while the tool tip travels
    at least `length` metres (wiping, combing, brushing)."""

    a: Point
    b: Point
    radius: float
    length: float


@dataclass(frozen=True)
class Dwell:
    """The tool tip within `radius` of a point for `seconds` without a break (the spoon at the mouth)."""

    point: Point
    radius: float
    seconds: float


@dataclass
class Task:
    name: str
    tool: str | None
    multimodal: bool
    sample_objects: Callable[[np.random.Generator], dict[str, tuple[float, float, float, float]]]
    plan: Callable[[Scene], list[tuple[np.ndarray, float]]]  # (tool-tip or tcp target, dwell seconds)
    touches: list[tuple[Point, float]] = field(default_factory=list)  # reached in order by the tool tip
    stroke: Stroke | None = None  # tool contact along a stroke on the manikin
    dwell: Dwell | None = None  # the tool tip held at a point (after the touches)
    placed: Callable[[Scene], bool] | None = None  # final predicate on the objects

    @property
    def modes(self) -> tuple[float, ...]:
        return (-1.0, 1.0) if self.multimodal else (1.0,)

    @property
    def slug(self) -> str:
        return self.name.replace(" ", "_")

    def sample(self, rng: np.random.Generator) -> SceneSpec:
        poses = {"manikin": (float(rng.uniform(-0.04, 0.04)), float(rng.uniform(0.50, 0.54)), 0.0,
                             float(rng.uniform(-0.1, 0.1)))}
        poses.update(self.sample_objects(rng))
        mode = int(rng.choice([-1, 1])) if self.multimodal else 1
        return SceneSpec(task=self.name, poses=poses, tool=self.tool, extras={"mode": float(mode)})

    def tcp_keypoints(self, scene: Scene) -> list[tuple[np.ndarray, float]]:
        """The planned keypoints as tcp targets (the plan gives tool-tip targets for a held tool)."""
        offset = -tool_tip_offset(self.tool)
        return [(np.asarray(p, float) + offset, dwell) for p, dwell in self.plan(scene)]


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _pose(x: float, y: float, z: float = 0.0, yaw: float = 0.0) -> tuple[float, float, float, float]:
    return (x, y, z, yaw)


def _xy_dist(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a[:2] - b[:2]))


def _v(*xyz: float) -> np.ndarray:
    return np.array(xyz, float)


# --- object tasks -------------------------------------------------------------------------------------------
def _sweep_objects(rng: np.random.Generator) -> dict:
    tx, ty = _u(rng, -0.10, 0.10), _u(rng, 0.20, 0.26)  # the broom going round it stays clear of the hands
    return {"trash": _pose(tx, ty), "dustpan": _pose(tx + _u(rng, -0.03, 0.03), ty - _u(rng, 0.14, 0.18))}


def _sweep_plan(s: Scene) -> list:
    t, dp = s.body("trash"), s.body("dustpan")
    side = 0.14 * s.mode  # go round the trash, low, on the left or the right: the average of both hits it
    return [
        (_v(t[0] + side, t[1] - 0.02, 0.025), 0.0),
        (_v(t[0] + side, t[1] + 0.065, 0.025), 0.0),
        (_v(t[0], t[1] + 0.065, 0.025), 0.0),
        (_v(t[0], t[1] + 0.065, 0.012), 0.1),
        (_v(dp[0], dp[1] + 0.025, 0.012), 0.1),
        (_v(dp[0], dp[1] + 0.04, 0.08), 0.0),
    ]


def _in_dustpan(s: Scene) -> bool:
    """The trash's centre lies on the dustpan's footprint."""
    d = s.body("trash") - s.body("dustpan")
    return abs(d[0]) < DUSTPAN_HALF[0] and abs(d[1]) < DUSTPAN_HALF[1]


def _pass_objects(rng: np.random.Generator) -> dict:
    return {"cup": _pose(_u(rng, -0.22, -0.02), _u(rng, 0.14, 0.26), 0.0, _u(rng, -0.5, 0.5))}


def _hand_place(s: Scene) -> np.ndarray:
    return s.site("hand_rest") + _v(-0.09, -0.02, -0.04)


def _pass_plan(s: Scene) -> list:
    g, c = s.site("cup_grasp"), s.body("cup")
    tgt = _hand_place(s) + (g - c)
    return [
        (_v(g[0] + 0.10 * s.mode, g[1] - 0.03, 0.20), 0.0),  # approach from the left or the right side
        (g + _v(0, 0, 0.05), 0.0),
        (g + GRASP_DEPTH, 0.8),  # reach through the grasp site and settle (the 32 resampled waypoints keep it)
        (g + _v(0, 0, 0.10), 0.0),
        (tgt + _v(0, 0, 0.08), 0.0),
        (tgt + _v(0, 0, 0.005), 0.15),
    ]


def _towel_objects(rng: np.random.Generator) -> dict:
    return {"towel": _pose(_u(rng, -0.25, -0.08), _u(rng, 0.14, 0.26), 0.0, _u(rng, -0.3, 0.3)),
            "rack": _pose(_u(rng, 0.10, 0.22), _u(rng, 0.26, 0.36))}


def _towel_plan(s: Scene) -> list:
    c = s.body("towel")
    g = s.site("towel_grasp_r" if s.mode > 0 else "towel_grasp_l")  # two grasp sides of the towel
    rack_top = s.body("rack") + _v(0, 0, 0.204)
    tgt = rack_top + (g - c) + _v(0, 0, 0.01)
    return [
        (g + _v(0, 0, 0.06), 0.0),
        (g + GRASP_DEPTH, 0.8),  # reach through the grasp site and settle (the 32 resampled waypoints keep it)
        (g + _v(0, 0, 0.26), 0.0),
        (tgt + _v(0, 0, 0.06), 0.0),
        (tgt, 0.15),
    ]


def _hat_objects(rng: np.random.Generator) -> dict:
    return {"hat": _pose(_u(rng, 0.06, 0.24), _u(rng, 0.10, 0.22), 0.0, _u(rng, -1, 1))}


def _hat_plan(s: Scene) -> list:
    g, c = s.site("hat_grasp"), s.body("hat")
    tgt = s.site("head_top") + (g - c)
    return [
        (g + _v(0, 0, 0.06), 0.0),
        (g + GRASP_DEPTH, 0.8),  # reach through the grasp site and settle (the 32 resampled waypoints keep it)
        (g + _v(0, 0, 0.20), 0.0),
        (tgt + _v(0.12 * s.mode, -0.10, 0.06), 0.0),  # come in over the left or the right shoulder
        (tgt + _v(0, 0, 0.04), 0.0),
        (tgt + _v(0, 0, 0.02), 0.15),  # let go 2 cm above the hair: the hat settles on the head
    ]


def _cover_objects(rng: np.random.Generator) -> dict:
    lx, ly = _u(rng, -0.26, -0.14), _u(rng, 0.12, 0.26)
    px, py = _u(rng, 0.08, 0.22), _u(rng, 0.16, 0.30)
    mid = ((lx + px) / 2 + _u(rng, -0.02, 0.02), (ly + py) / 2 + _u(rng, -0.02, 0.02))
    return {"lid": _pose(lx, ly), "plate": _pose(px, py), "bottle": _pose(*mid)}


def _cover_plan(s: Scene) -> list:
    g, c, p, b = s.site("lid_grasp"), s.body("lid"), s.body("plate"), s.body("bottle")
    tgt = p + (g - c) + _v(0, 0, 0.014)
    return [
        (g + _v(0, 0, 0.06), 0.0),
        (g + GRASP_DEPTH, 0.8),  # reach through the grasp site and settle (the 32 resampled waypoints keep it)
        (g + _v(0, 0, 0.10), 0.0),
        (_v(b[0], b[1] + 0.15 * s.mode, g[2] + 0.10), 0.0),  # pass the bottle on either side (it blocks the middle)
        (tgt + _v(0, 0, 0.06), 0.0),
        (tgt, 0.15),
    ]


# --- tool tasks (targets are tool-tip positions) --------------------------------------------------------------
def _no_objects(rng: np.random.Generator) -> dict:
    return {}


def _nose_plan(s: Scene) -> list:
    # The sponge's front face is 2 cm ahead of its tip: press it 3 mm into the nose and wipe 2 cm each way.
    n = s.site("nose") + _v(0, -0.017, 0)
    return [
        (n + _v(0, -0.08, 0.02), 0.0),
        (n, 0.1),
        (n + _v(0.02, 0, 0), 0.0),
        (n + _v(-0.02, 0, 0), 0.0),
        (n + _v(0, -0.08, 0.02), 0.0),
    ]


FOREARM_PRESS = _v(0, 0, -0.001)  # the sponge's bottom face 1 mm into the skin


def _forearm_plan(s: Scene) -> list:
    a, b = s.site("forearm_start") + FOREARM_PRESS, s.site("forearm_end") + FOREARM_PRESS
    if s.mode < 0:  # stroke in either direction
        a, b = b, a
    # Come down slowly for the last centimetre: touching down fast on the skin is an impact.
    return [(a + _v(0, 0, 0.07), 0.0), (a + _v(0, 0, 0.01), 0.0), (a, 0.1), (b, 0.0), (a, 0.0), (b, 0.1),
            (b + _v(0, 0, 0.07), 0.0)]


def _feed_objects(rng: np.random.Generator) -> dict:
    return {"bowl": _pose(_u(rng, -0.22, 0.0), _u(rng, 0.14, 0.26))}


def _bowl_point(s: Scene) -> np.ndarray:
    return s.body("bowl") + _v(0, 0, 0.035)


def _feed_plan(s: Scene) -> list:
    bw, mo = _bowl_point(s), s.site("mouth")
    return [
        (bw + _v(0, 0, 0.08), 0.0),
        (bw, 0.1),
        (bw + _v(0.02, 0, 0.0), 0.0),
        (bw + _v(0, 0, 0.10), 0.0),
        (mo + _v(0.08 * s.mode, -0.10, 0.0), 0.0),  # bring the spoon up from the left or the right
        (mo + _v(0, -0.012, 0), 0.3),
        (mo + _v(0, -0.10, 0.02), 0.0),
    ]


def _comb_plan(s: Scene) -> list:
    # Front, over the top, to the back of the hair sphere, the comb's edge 2-3 mm into the hair.
    f, m, b = s.site("hair_front"), s.site("hair_mid"), s.site("hair_back") + _v(0, 0, -0.004)
    return [(f + _v(0, -0.06, 0.06), 0.0), (f + _v(0, -0.01, 0.01), 0.0), (f, 0.05), (m, 0.0), (b, 0.0),
            (m + _v(0, 0, 0.03), 0.0), (f + _v(0, 0, 0.02), 0.0), (f, 0.0), (m, 0.0), (b, 0.05),
            (b + _v(0, 0, 0.06), 0.0)]


def _teeth_plan(s: Scene) -> list:
    mo = s.site("mouth") + _v(0, 0.004, 0)  # the brush head (radius 5 mm) 4 mm into the mouth
    return [
        (mo + _v(0, -0.10, 0.0), 0.0),
        (mo, 0.05),
        (mo + _v(0.015, 0, 0), 0.0),
        (mo + _v(-0.015, 0, 0), 0.0),
        (mo + _v(0.015, 0, 0), 0.0),
        (mo + _v(0, -0.10, 0.0), 0.0),
    ]


def _site(name: str, offset: tuple[float, float, float] = (0, 0, 0)) -> Point:
    return lambda s: s.site(name) + np.asarray(offset)


TASKS: dict[str, Task] = {
    t.name: t
    for t in [
        Task("sweep the trash", "broom", True, _sweep_objects, _sweep_plan,
             placed=lambda s: _in_dustpan(s)),
        Task("pass the water", None, True, _pass_objects, _pass_plan,
             placed=lambda s: _xy_dist(s.body("cup"), _hand_place(s)) < 0.06 and s.upright("cup") > 0.9),
        Task("hang the towel", None, True, _towel_objects, _towel_plan,
             placed=lambda s: _xy_dist(s.body("towel"), s.body("rack")) < 0.08 and s.body("towel")[2] > 0.17),
        Task("put on the hat", None, True, _hat_objects, _hat_plan,
             placed=lambda s: _xy_dist(s.body("hat"), s.site("head_top")) < 0.05
             and s.body("hat")[2] > s.site("head_top")[2] - 0.06),
        Task("cover the food", None, True, _cover_objects, _cover_plan,
             placed=lambda s: _xy_dist(s.body("lid"), s.body("plate")) < 0.035 and s.body("lid")[2] < 0.05),
        Task("wipe the nose", "sponge", False, _no_objects, _nose_plan,
             stroke=Stroke(_site("nose"), _site("nose"), 0.03, 0.03)),
        Task("wipe the forearm", "sponge", True, _no_objects, _forearm_plan,
             stroke=Stroke(_site("forearm_start"), _site("forearm_end"), 0.03, 0.10)),
        Task("feed the human", "spoon", True, _feed_objects, _feed_plan, touches=[(_bowl_point, 0.03)],
             dwell=Dwell(_site("mouth"), 0.02, 0.15)),
        Task("comb the hair", "comb", False, _no_objects, _comb_plan,
             stroke=Stroke(_site("hair_front"), _site("hair_back"), 0.03, 0.08)),
        Task("brush the teeth", "toothbrush", False, _no_objects, _teeth_plan,
             stroke=Stroke(_site("mouth"), _site("mouth"), 0.025, 0.03)),
    ]
}


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    s = float(np.clip(np.dot(p - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + s * ab)))


class SuccessMonitor:
    """Follows the execution step by step and judges the task's success predicate at the end:
    - no contact on the manikin above FORCE_LIMIT_N, ever (from the arm, a tool or a held object);
    - `touches` reached in order by the tool tip;
    - `stroke`: the tip's path length while the tool touches the manikin near the stroke segment;
    - `dwell`: the tip held near a point for long enough without a break;
    - `placed`: the final predicate on the objects.
    """

    def __init__(self, task: Task, scene: Scene) -> None:
        self.task, self.scene = task, scene
        m = scene.m
        self.reached = 0
        self.tip_site = m.site("tool_tip").id if task.tool else m.site("tcp").id
        # The person: the manikin and, when the person moves, its head and forearm (adlpipe.sim.person)
        self.person = {i for i in range(m.nbody) if m.body(i).name.startswith("manikin")}
        self.moving = bool(scene.spec.person)
        self.tool = m.body("tool").id if task.tool else -1
        self.stroked = 0.0
        self.dwelt, self.longest_dwell = 0.0, 0.0
        self._locate()
        self.max_force = 0.0
        self._prev_tip: np.ndarray | None = None
        self._prev_time = float(scene.d.time)
        self._f6 = np.zeros(6)

    def _locate(self) -> None:
        """Where the targets are now: once for a still person, at every step for one who moves (the spoon must
        reach the mouth where the mouth is then)."""
        t, s = self.task, self.scene
        self.targets = [(fn(s), r) for fn, r in t.touches]
        self.stroke = (t.stroke.a(s), t.stroke.b(s)) if t.stroke else None
        self.dwell_point = t.dwell.point(s) if t.dwell else None

    def _manikin_contacts(self) -> tuple[float, bool]:
        """(largest normal force on the manikin now, whether the tool touches it near the stroke)."""
        m, d = self.scene.m, self.scene.d
        force, stroking = 0.0, False
        for i in range(d.ncon):
            c = d.contact[i]
            b1, b2 = m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]
            if b1 not in self.person and b2 not in self.person:
                continue
            mujoco.mj_contactForce(m, d, i, self._f6)
            force = max(force, abs(float(self._f6[0])))
            if self.stroke is not None and self.tool in (b1, b2):
                stroking |= _segment_distance(c.pos, *self.stroke) < self.task.stroke.radius
        return force, stroking

    def step(self) -> None:
        d = self.scene.d
        if self.moving:
            self._locate()
        tip = d.site_xpos[self.tip_site].copy()
        dt = float(d.time) - self._prev_time
        force, stroking = self._manikin_contacts()
        self.max_force = max(self.max_force, force)
        if stroking and self._prev_tip is not None:
            self.stroked += float(np.linalg.norm(tip - self._prev_tip))
        if self.reached < len(self.targets):
            p, r = self.targets[self.reached]
            if np.linalg.norm(tip - p) < r:
                self.reached += 1
        elif self.dwell_point is not None:
            near = np.linalg.norm(tip - self.dwell_point) < self.task.dwell.radius
            self.dwelt = self.dwelt + dt if near else 0.0
            self.longest_dwell = max(self.longest_dwell, self.dwelt)
        self._prev_tip, self._prev_time = tip, float(d.time)

    def checks(self) -> dict[str, bool]:
        """Each part of the predicate (for reports and debugging)."""
        t = self.task
        out = {"force": self.max_force <= FORCE_LIMIT_N, "touches": self.reached == len(self.targets)}
        if t.stroke:
            out["stroke"] = self.stroked >= t.stroke.length
        if t.dwell:
            out["dwell"] = self.longest_dwell >= t.dwell.seconds
        if t.placed:
            out["placed"] = bool(t.placed(self.scene))
        return out

    def success(self) -> bool:
        return all(self.checks().values())
