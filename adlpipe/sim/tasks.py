"""The 10 ADL tasks of the paper: scene randomisation, a scripted demonstrator and a success predicate each.

Demonstrations are multimodal where the task allows (approach left or right of an obstacle, two grasp sides,
stroke direction), so a regressor trained with MSE averages the modes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np

from .world import DUSTPAN_HALF, TOOL_LENGTH, SceneSpec

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


@dataclass
class Task:
    name: str
    tool: str | None
    multimodal: bool
    sample_objects: Callable[[np.random.Generator], dict[str, tuple[float, float, float, float]]]
    plan: Callable[[Scene], list[tuple[np.ndarray, float]]]  # (tool-tip or tcp target, dwell seconds)
    touches: list[tuple[Point, float]] = field(default_factory=list)  # reached in order by the tool tip
    placed: Callable[[Scene], bool] | None = None  # final predicate on the objects

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
        """The planned keypoints as tcp targets (a held tool's tip is TOOL_LENGTH below the tcp)."""
        offset = np.array([0.0, 0.0, TOOL_LENGTH if self.tool else 0.0])
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
    tx, ty = _u(rng, -0.10, 0.10), _u(rng, 0.26, 0.34)
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
        (g, 0.15),
        (g + _v(0, 0, 0.10), 0.0),
        (tgt + _v(0, 0, 0.08), 0.0),
        (tgt + _v(0, 0, 0.005), 0.15),
    ]


def _towel_objects(rng: np.random.Generator) -> dict:
    return {"towel": _pose(_u(rng, -0.25, -0.08), _u(rng, 0.14, 0.26), 0.0, _u(rng, -0.3, 0.3)),
            "rack": _pose(_u(rng, 0.10, 0.22), _u(rng, 0.26, 0.36))}


def _towel_plan(s: Scene) -> list:
    c = s.body("towel")
    side = _v(0.02 * s.mode, 0, 0)  # two grasp sides of the towel
    g = s.site("towel_grasp") + side
    rack_top = s.body("rack") + _v(0, 0, 0.204)
    tgt = rack_top + (g - c) + _v(0, 0, 0.01)
    return [
        (g + _v(0, 0, 0.06), 0.0),
        (g, 0.15),
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
        (g, 0.15),
        (g + _v(0, 0, 0.20), 0.0),
        (tgt + _v(0.12 * s.mode, -0.10, 0.06), 0.0),  # come in over the left or the right shoulder
        (tgt + _v(0, 0, 0.04), 0.0),
        (tgt + _v(0, 0, 0.012), 0.15),
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
        (g, 0.15),
        (g + _v(0, 0, 0.10), 0.0),
        (_v(b[0], b[1] + 0.15 * s.mode, g[2] + 0.10), 0.0),  # pass the bottle on either side (it blocks the middle)
        (tgt + _v(0, 0, 0.06), 0.0),
        (tgt, 0.15),
    ]


# --- tool tasks (targets are tool-tip positions) --------------------------------------------------------------
def _no_objects(rng: np.random.Generator) -> dict:
    return {}


def _nose_plan(s: Scene) -> list:
    n = s.site("nose")
    return [
        (n + _v(0, -0.10, 0.02), 0.0),
        (n + _v(0, -0.012, 0), 0.1),
        (n + _v(0.02, -0.012, 0), 0.0),
        (n + _v(-0.02, -0.012, 0), 0.0),
        (n + _v(0, -0.10, 0.02), 0.0),
    ]


def _forearm_plan(s: Scene) -> list:
    a, b = s.site("forearm_start") + _v(0, 0, 0.02), s.site("forearm_end") + _v(0, 0, 0.02)
    if s.mode < 0:  # stroke in either direction
        a, b = b, a
    return [(a + _v(0, 0, 0.07), 0.0), (a, 0.1), (b, 0.0), (a, 0.0), (b, 0.1), (b + _v(0, 0, 0.07), 0.0)]


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
        (mo + _v(0, -0.01, 0), 0.2),
        (mo + _v(0, -0.10, 0.02), 0.0),
    ]


def _comb_plan(s: Scene) -> list:
    f, b = s.site("hair_front") + _v(0, 0, 0.012), s.site("hair_back") + _v(0, 0, 0.012)
    return [(f + _v(0, -0.06, 0.06), 0.0), (f, 0.05), (b, 0.0), (f + _v(0, 0, 0.03), 0.0), (f, 0.0), (b, 0.05),
            (b + _v(0, 0, 0.06), 0.0)]


def _teeth_plan(s: Scene) -> list:
    mo = s.site("mouth")
    return [
        (mo + _v(0, -0.10, 0.0), 0.0),
        (mo + _v(0, -0.01, 0), 0.05),
        (mo + _v(0.015, -0.01, 0), 0.0),
        (mo + _v(-0.015, -0.01, 0), 0.0),
        (mo + _v(0.015, -0.01, 0), 0.0),
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
        Task("wipe the nose", "sponge", False, _no_objects, _nose_plan, touches=[(_site("nose"), 0.025)]),
        Task("wipe the forearm", "sponge", True, _no_objects, _forearm_plan,
             touches=[(_site("forearm_start", (0, 0, 0.02)), 0.03), (_site("forearm_end", (0, 0, 0.02)), 0.03)]),
        Task("feed the human", "spoon", True, _feed_objects, _feed_plan,
             touches=[(_bowl_point, 0.03), (_site("mouth"), 0.025)]),
        Task("comb the hair", "comb", False, _no_objects, _comb_plan,
             touches=[(_site("hair_front", (0, 0, 0.012)), 0.03), (_site("hair_back", (0, 0, 0.012)), 0.03)]),
        Task("brush the teeth", "toothbrush", False, _no_objects, _teeth_plan, touches=[(_site("mouth"), 0.025)]),
    ]
}


class SuccessMonitor:
    """Follows the tool tip during execution; judges the task's success predicate at the end."""

    def __init__(self, task: Task, scene: Scene) -> None:
        self.task, self.scene = task, scene
        self.targets = [(fn(scene), r) for fn, r in task.touches]  # the manikin does not move
        self.reached = 0
        self.tip_site = scene.m.site("tool_tip").id if task.tool else scene.m.site("tcp").id
        # Forearm strokes may start at either end: touching both in any order counts.
        self.any_order = task.name == "wipe the forearm"
        self.touched: set[int] = set()

    def step(self) -> None:
        tip = self.scene.d.site_xpos[self.tip_site]
        for i, (p, r) in enumerate(self.targets):
            if np.linalg.norm(tip - p) < r:
                self.touched.add(i)
        if self.reached < len(self.targets):
            p, r = self.targets[self.reached]
            if np.linalg.norm(tip - p) < r:
                self.reached += 1

    def success(self) -> bool:
        touched = (len(self.touched) == len(self.targets)) if self.any_order else (
            self.reached == len(self.targets))
        placed = self.task.placed(self.scene) if self.task.placed else True
        return bool(touched and placed)
