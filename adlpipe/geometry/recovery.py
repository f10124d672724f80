"""The demonstrator's way back to its path (DART-style recovery demonstrations, Laskey et al., CoRL 2017).

A demonstrator recorded with `record --recoveries` is disturbed off its reference path now and then; from wherever
its command is, it returns to the reference, the offset fading exponentially (a proportional pull). The same law
makes the training labels of `train --target recovery`: the plan the demonstrator would follow from the command at
a frame, whatever disturbance was under way there, so no label ever shows the disturbance itself.
"""

from __future__ import annotations

import numpy as np

from .transforms import path_at

RETURN_TAU_S = 0.3  # the time constant of the return: 95 % of an offset gone in 0.9 s
RETURN_S = 3 * RETURN_TAU_S  # what a disturbance leaves free after it for the return


def offset_left(elapsed: np.ndarray) -> np.ndarray:
    """The share of an offset from the reference still left `elapsed` seconds into the return. Exponential: a
    plan made anywhere along a return is the rest of that return, so the labels of frames on the way back are
    what the demonstrator then did."""
    return np.exp(-np.maximum(np.asarray(elapsed, float), 0.0) / RETURN_TAU_S)


def recovering_plan(t_now: np.ndarray, now: np.ndarray, ref_t: np.ndarray, ref_p: np.ndarray,
                    future: np.ndarray) -> np.ndarray:
    """(F, H, 3): the demonstrator's plan from the command `now` (F, 3) at times t_now (F,), at the absolute times
    `future` (F, H): the reference path there, plus the command's offset from the reference at t_now, fading."""
    t_now = np.asarray(t_now, float)
    ref_future = path_at(future, ref_t, ref_p[:, :3])
    ref_now = path_at(t_now, ref_t, ref_p[:, :3])
    left = offset_left(future - t_now[:, None])
    return ref_future + (np.asarray(now, float) - ref_now)[:, None] * left[..., None]
