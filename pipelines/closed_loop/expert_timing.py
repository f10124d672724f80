"""How far a round's rollouts are from the demonstration's timetable, against how far they are from its path.

    python expert_timing.py data/dagger/r1/fm_cnn/adl.h5 --split ../../data/split.json -o metrics/expert_timing.json

Per frame of every rollout (the episodes the default split does not name): the command's distance from the
demonstrated path at the same time (what a timed expert's label makes up) and from the path anywhere along it (what
being off the path means), the phase lag (the frame's time less the time of the path point nearest the command),
and where the rollouts recorded the expert's phase, the command's distance from the path at that phase (what the
phase expert's label makes up). A timed expert whose offsets are mostly lag teaches a dash along the path, not a
way back to it (docs/science/dagger.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import h5py
import numpy as np

from adlpipe.dataset.loader import command_series, reference_series
from adlpipe.geometry.transforms import path_at
from adlpipe.sim.dagger import Expert


def timing(data: Path, demos: set[str]) -> dict:
    timed, geometric, lag, phased = [], [], [], []
    with h5py.File(data) as f:
        for name, g in f["episodes"].items():
            if name in demos:
                continue
            ct, cmd = command_series(g, name)
            rt, rp = reference_series(g, name)
            t = g["frames/t"][()]
            c = path_at(t, ct, cmd)
            r = path_at(t, rt, rp)
            timed.append(np.linalg.norm(c - r, axis=1))
            geometric.append(Expert(rt, rp, 16, 10.0).off_path(c))
            grid = np.linspace(0.0, rt[-1], 2000)
            path = path_at(grid, rt, rp)
            lag.append(t - grid[np.argmin(np.linalg.norm(c[:, None] - path[None], axis=2), axis=1)])
            if "expert_phase_stream" in g["frames"]:  # the phase expert's offset: from the path at its phase
                at = np.interp(t, g["frames/expert_phase_stream_t"][()], g["frames/expert_phase_stream"][:, 0])
                r = path_at(at, rt, rp)
                phased.append(np.linalg.norm(c - r, axis=1))
    a, b, lg = (np.concatenate(x) for x in (timed, geometric, lag))
    cm = lambda x, q: round(100 * float(np.percentile(x, q)), 1)  # noqa: E731
    return {"frames": len(a), "rollouts": len(timed),
            "timed_offset_cm": {"median": cm(a, 50), "p90": cm(a, 90)},
            "off_path_cm": {"median": cm(b, 50), "p90": cm(b, 90)},
            "phase_lag_s": {q: round(float(np.percentile(lg, p)), 2) for q, p in (("p10", 10), ("median", 50),
                                                                                   ("p90", 90))},
            "share_timed_over_twice_off_path_plus_1cm": round(float(np.mean(a > 2 * b + 0.01)), 3),
            **({"phase_offset_cm": {"median": cm(np.concatenate(phased), 50), "p90": cm(np.concatenate(phased), 90)}}
               if phased else {})}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path)
    p.add_argument("--split", type=Path, required=True, help="the default split: the demonstrations it names")
    p.add_argument("-o", "--out", type=Path, required=True)
    args = p.parse_args()
    split = json.loads(args.split.read_text())
    demos = set(split["train"]) | set(split["test"])
    out = {"data": str(args.data), **timing(args.data, demos)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
