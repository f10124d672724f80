"""How well the doctor's gripper-inversion check separates an inverted gripper reading from a clean one.

    python bench/gripper_inverted.py data/adl.h5 [-o results/bench/gripper_inverted.txt]

Per episode, with the doctor's own figures (doctor.examine): its gripper profile's mean distance from the median
of its task's other episodes as stored, and the same for the profile upside down (what an inverted reading would
show); the doctor flags an episode whose distance exceeds Limits.gripper_off while upside down it is under
Limits.swap_gain of it. The inverted case swaps the two distances.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from adlpipe.curation.doctor import Limits, examine
from adlpipe.curation.doctor_checks import by_task


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path)
    p.add_argument("-o", "--out", type=Path)
    a = p.parse_args()
    figs, lim = examine(str(a.data)), Limits()
    stored, upside = [], []
    for members in by_task(figs).values():
        profiled = [n for n in members if figs[n]["gripper_profile"]]
        for n in profiled if len(profiled) >= 3 else []:
            others = np.median([figs[m]["gripper_profile"] for m in profiled if m != n], 0)
            prof = np.asarray(figs[n]["gripper_profile"])
            stored.append(float(np.abs(prof - others).mean()))
            upside.append(float(np.abs(1 - prof - others).mean()))
    s, u = np.array(stored), np.array(upside)
    flagged = lambda x, y: (x > lim.gripper_off) & (y < lim.swap_gain * x)  # noqa: E731
    text = (f"{a.data}: {len(s)} episodes with a moving gripper in tasks of 3 or more\n"
            f"clean: distance from the task's others max {s.max():.3f} (limit {lim.gripper_off}); flagged "
            f"{int(flagged(s, u).sum())}\n"
            f"inverted: distance min {u.min():.3f}, upside down over as stored at most {(s / u).max():.3f} "
            f"(limit {lim.swap_gain}); flagged {int(flagged(u, s).sum())} of {len(u)}\n")
    print(text, end="")
    if a.out:
        a.out.write_text(text)


if __name__ == "__main__":
    main()
