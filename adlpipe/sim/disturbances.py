"""Disturbances of the scripted demonstrator, for demonstrations with recoveries (`record --recoveries`).

The scripted demonstrator never leaves its own path, so a closed-loop policy trained on it never sees a way back
once its own plans take the arm off that path (covariate shift, docs/science/closed-loop.md). Here the commanded
tcp is now and then pushed off the path (an offset of 2-5 cm in a random direction) or held back (a stall, as a
plan that moves the arm too little), and the demonstrator then returns along adlpipe.geometry.recovery's law. The
reference path is recorded beside the command, so training labels are the demonstrator's plans, never the
disturbance itself (DART, Laskey et al., CoRL 2017).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..geometry.recovery import RETURN_S, offset_left

RISE_S = 0.2  # an offset builds up over this long
OFFSET_M = (0.02, 0.05)  # its size; replayed policies' re-plans start > 2 cm off the path in 36-62 % of cases
STALL_S = (0.15, 0.35)  # how long a stall holds the command (4-10 cm behind at the demonstrator's 0.3 m/s)
FIRST_S = 0.3  # no disturbance before this (the first plan starts at home)
END_MARGIN_S = 0.2  # the demonstrator is back on its path at least this long before the end


@dataclass(frozen=True)
class Disturbance:
    """From t0 to t1 the command leaves the path: by `offset` (reached at t1), or held where it was at t0 (a stall,
    offset None); from t1 it returns (adlpipe.geometry.recovery), the next one starting RETURN_S later at the
    earliest."""

    t0: float
    t1: float
    offset: np.ndarray | None = None


def draw_disturbances(rng: np.random.Generator, duration: float) -> list[Disturbance]:
    """Disturbances of one demonstration, one after another's return, offsets and stalls alike likely, all over
    before the end."""
    events: list[Disturbance] = []
    t = FIRST_S + rng.uniform(0.0, 0.5)
    while True:
        if rng.random() < 0.5:
            direction = rng.normal(size=3)
            ev = Disturbance(t, t + RISE_S, direction / np.linalg.norm(direction) * rng.uniform(*OFFSET_M))
        else:
            ev = Disturbance(t, t + rng.uniform(*STALL_S))
        if ev.t1 + RETURN_S > duration - END_MARGIN_S:
            return events
        events.append(ev)
        t = ev.t1 + RETURN_S + rng.uniform(0.2, 0.8)


def disturbed_path(path: Callable[[float], np.ndarray],
                   events: list[Disturbance]) -> Callable[[float], np.ndarray]:
    """The commanded path: `path` (the reference) plus an offset that each disturbance builds and each return
    fades (what is left of one return carries into the next disturbance)."""
    at_end: list[np.ndarray] = []  # the offset at each disturbance's end, where its return starts

    def offset(t: float) -> np.ndarray:
        i = next((i for i in range(len(events) - 1, -1, -1) if events[i].t0 <= t), None)
        if i is None:
            return np.zeros(3)
        ev = events[i]
        if t >= ev.t1 and i < len(at_end):
            return at_end[i] * offset_left(np.array(t - ev.t1))
        before = at_end[i - 1] * offset_left(np.array(ev.t0 - events[i - 1].t1)) if i else np.zeros(3)
        if ev.offset is None:  # a stall: the command stays where it was at the onset
            return path(ev.t0) + before - path(t)
        s = min((t - ev.t0) / (ev.t1 - ev.t0), 1.0)
        return before + ev.offset * (10 * s**3 - 15 * s**4 + 6 * s**5)  # minimum jerk

    for ev in events:  # in time order: each end's offset needs the ones before it
        at_end.append(offset(ev.t1))
    return lambda t: path(t) + offset(t)
