"""The blind baseline: a policy that ignores the image and always predicts its task's mean training trajectory.

It is the floor a trained model is measured against: what knowing the task alone buys. Every table that ranks
models carries it as a row ("blind"). The means are accumulated one training episode at a time (memory flat in
the number of episodes), in the same units the models are scored in: traj2d in stored-image pixels, traj3d in
metres of the base frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..dataset import schema
from ..plumbing.errors import AdlError

BLIND = "blind"


def task_means(data: Path, train: list[str]) -> dict[str, np.ndarray]:
    """task -> mean (N, 5) trajectory (u, v, x, y, z) over the named training episodes of that task."""
    sums: dict[str, np.ndarray] = {}
    counts: dict[str, int] = {}
    with schema.open_dataset(data, train) as f:
        for name in train:
            g = f[schema.EPISODES][name]
            task = str(g.attrs["task"])
            traj = np.concatenate([g["traj2d"][()], g["traj3d"][()]], axis=1).astype(np.float64)
            if task in sums and sums[task].shape != traj.shape:
                raise AdlError(f"{data}: episode {name} has {traj.shape[0]} waypoints, its task's others "
                               f"{sums[task].shape[0]}")
            sums[task] = sums.get(task, 0.0) + traj
            counts[task] = counts.get(task, 0) + 1
    return {t: sums[t] / counts[t] for t in sums}


def blind_predictions(means: dict[str, np.ndarray], tasks: list[str]) -> np.ndarray:
    """(E, N, 5) predictions for test episodes of the given tasks; a task without training episodes is an error
    (the baseline has nothing to predict from)."""
    missing = sorted(set(tasks) - set(means))
    if missing:
        raise AdlError(f"blind baseline: no training episodes of task(s) {missing}")
    return np.stack([means[t] for t in tasks]).astype(np.float32)
