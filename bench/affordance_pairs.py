"""The doctor's affordance check against maps of other tasks (issue E3): every demonstration of a dataset judged
against every other task's episodes' maps, as if that map had been stored with it; the share of pairs under the
flag's limit, and the clean episodes' own figures.

    python bench/affordance_pairs.py data/adl.h5 > results/bench/affordance_pairs.txt
"""

from __future__ import annotations

import sys

import h5py
import numpy as np

from adlpipe.curation.doctor import Limits
from adlpipe.curation.doctor_checks import affordance_on_path
from adlpipe.dataset.schema import EPISODES


class WithMap:
    """An episode group read as stored, with another episode's affordance map in place of its own."""

    def __init__(self, g: h5py.Group, affordance: np.ndarray) -> None:
        self.g, self.map, self.attrs = g, affordance, g.attrs

    def __getitem__(self, key: str) -> object:
        return self.map if key == "affordance" else self.g[key]

    def __contains__(self, key: str) -> bool:
        return key in self.g


def main() -> None:
    limit = Limits().affordance_dwell
    with h5py.File(sys.argv[1]) as f:
        eps = f[EPISODES]
        names = list(eps)
        task = {n: str(eps[n].attrs["task"]) for n in names}
        maps = {n: eps[n]["affordance"][()] for n in names}
        own = [affordance_on_path(eps[n])["affordance_dwell"] for n in names]
        worst: dict[tuple[str, str], float] = {}
        crossed = []
        for n in names:
            for o in names:
                if task[o] != task[n]:
                    x = affordance_on_path(WithMap(eps[n], maps[o]))["affordance_dwell"]
                    if x is not None:
                        crossed.append(x)
                        worst[task[n], task[o]] = max(worst.get((task[n], task[o]), 0.0), x)
    judged = [x for x in own if x is not None]
    print(f"{sys.argv[1]}: {len(names)} episodes, {len(judged)} judged; own map: min {min(judged):.3f}, "
          f"median {np.median(judged):.3f}; flagged (under {limit}): {sum(x < limit for x in judged)}")
    print(f"another task's map: {len(crossed)} pairs, {np.mean(np.array(crossed) < limit):.1%} under {limit}")
    never = sorted(k for k, v in worst.items() if v >= limit)
    print(f"task pairs where some demonstration sits on the other's map ({len(never)} of {len(worst)}):")
    for a, b in never:
        print(f"  {a} <- {b}'s map: up to {worst[a, b]:.2f}")


if __name__ == "__main__":
    main()
