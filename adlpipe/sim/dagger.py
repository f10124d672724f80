"""The expert who labels a policy's own states (DAgger, Ross et al. 2011) and the operator who takes over when a
rollout leaves the path (HG-DAgger, Kelly et al. 2019), in the ADL world.

The expert is the demonstrator's own law (adlpipe.geometry.recovery): from wherever the command is, back onto the
scene's demonstrated path, the offset fading, and on along it to the goal, at the demonstration's pace from the point of
the path the rollout has reached (its phase), not from where the demonstration was at that time: a policy that lags
behind the demonstration's timetable is led on along the path, not told to dash to catch up (measured: timed labels
were mostly that dash, docs/science/dagger.md). The phase is tracked from the command as the rollout goes (the
nearest point of the path up to LOOK_AHEAD_S ahead, never back), and recorded (/adl/expert_phase); with the scene's
demonstrated path (the reference topic) it is what `train --target recovery` makes each frame's label from, so the
label of a re-plan's frame is the expert's plan there, which also goes on a topic of its own (/adl/expert_plan).

The operator watches the executed commands: off the path by more than `off_cm` for `hold_s`, it takes over and
drives with the expert's plans until the command is back within `back_cm`; the bag says when on a Bool topic (the
topic map's `intervention`, LeRobot's `intervention` feature). It decides at each re-plan (every Ta waypoints), as
the executor hands the arm to whoever plans next.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.recovery import recovering_plan
from ..geometry.transforms import path_at

if TYPE_CHECKING:
    from .episode import Streams

PATH_SPACING_M = 0.001  # the reference path resampled this finely: distances to it are within half of it
LOOK_AHEAD_S = 1.0  # the tracker looks this far along the path ahead of the phase at each step (100 Hz)


@dataclass(frozen=True)
class OperatorRule:
    """When the simulated operator takes over and hands back."""

    off_cm: float = 2.0  # off the path by more than this ...
    hold_s: float = 0.3  # ... for this long (the executed commands up to the re-plan): take over
    back_cm: float = 0.5  # hand back once the command is this close to the path again


class Expert:
    """The demonstrator's plans from any command, along the scene's demonstrated path (stamps, positions)."""

    def __init__(self, ref_t: np.ndarray, ref_p: np.ndarray, horizon: int, rate_hz: float) -> None:
        self.ref_t, self.ref_p = np.asarray(ref_t, float), np.asarray(ref_p, float)[:, :3]
        self.horizon, self.rate_hz = horizon, rate_hz
        self._tree = cKDTree(dense_path(self.ref_p))
        self.phase = 0.0

    def reference(self, t: float | np.ndarray) -> np.ndarray:
        """The demonstrated path at time(s) t of the demonstration (held at its end): (3,) or (len(t), 3)."""
        return path_at(t, self.ref_t, self.ref_p)

    def track(self, now: np.ndarray) -> float:
        """The phase (s along the demonstration) of the command `now`: the point of the path nearest it from the
        phase so far to LOOK_AHEAD_S ahead of it (never back; the earliest of equally near points, so a dwell or a
        stroke that passes the same place again is not skipped)."""
        end = min(self.phase + LOOK_AHEAD_S, float(self.ref_t[-1]))
        candidates = np.linspace(self.phase, end, 201)  # 5 ms apart
        distance = np.linalg.norm(self.reference(candidates) - np.asarray(now, float), axis=1)
        self.phase = float(candidates[int(np.argmin(distance))])
        return self.phase

    def plan(self, now: np.ndarray) -> np.ndarray:
        """(horizon, 3): the expert's waypoints 1/rate .. horizon/rate s from the command `now`: back onto the path
        and on from the phase the command has reached."""
        phase = self.track(now)
        future = phase + np.arange(1, self.horizon + 1)[None] / self.rate_hz
        return recovering_plan(np.array([phase]), np.asarray(now, float)[None], self.ref_t, self.ref_p, future)[0]

    def off_path(self, points: np.ndarray) -> np.ndarray:
        """Each point's distance (m) from the demonstrated path (anywhere along it, not at a time)."""
        return self._tree.query(np.asarray(points, float).reshape(-1, 3))[0]


def dense_path(p: np.ndarray) -> np.ndarray:
    """The polyline through p resampled every PATH_SPACING_M along its length (the points themselves kept)."""
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    out = [p[:1]]
    for a, b, n in zip(p[:-1], p[1:], np.ceil(seg / PATH_SPACING_M).astype(int), strict=True):
        if n > 0:
            out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


@dataclass
class Operator:
    """Takes over when the executed commands stay off the path; drives until the command is back."""

    expert: Expert
    rule: OperatorRule = field(default_factory=OperatorRule)
    driving: bool = False

    def decide(self, executed: np.ndarray, dt: float, anchor: np.ndarray) -> bool:
        """Whether the operator plans next: `executed` the commands (N, 3) since the last re-plan, dt apart,
        `anchor` the command now."""
        if self.driving:
            self.driving = self.expert.off_path(anchor)[0] > self.rule.back_cm / 100
        elif len(executed):
            off = self.expert.off_path(executed) > self.rule.off_cm / 100
            need = max(1, int(np.ceil(self.rule.hold_s / dt - 1e-9)))
            self.driving = len(off) >= need and bool(off[-need:].all())
        return self.driving


class LabelledRollout:
    """The plan function a closed-loop rollout runs with: the policy's plan, or the operator's when it drives;
    every re-plan's expert plan and who drove are kept in the rollout's streams (adlpipe.sim.episode.Streams)."""

    def __init__(self, policy_plan: Callable[[list, float, np.ndarray], np.ndarray], expert: Expert,
                 streams: Streams, execute: int,
                 operator: Operator | None = None) -> None:
        self.policy_plan, self.expert, self.st, self.execute = policy_plan, expert, streams, execute
        self.operator = operator
        self.last_plan: np.ndarray | None = None
        self.operator_plans = 0

    def __call__(self, frames: list, t: float, anchor: np.ndarray) -> np.ndarray:
        expert = self.expert.plan(anchor)
        self.st.expert_plans.append((t, expert.copy(), np.arange(1, len(expert) + 1) / self.expert.rate_hz))
        executed = self.last_plan[:self.execute] if self.last_plan is not None else np.zeros((0, 3))
        drives = self.operator is not None and self.operator.decide(executed, 1 / self.expert.rate_hz, anchor)
        if self.operator is not None:
            self.st.interventions.append((t, drives))
        plan = expert if drives else np.asarray(self.policy_plan(frames, t, anchor), dtype=float)
        self.operator_plans += int(drives)
        self.last_plan = plan
        return plan
