"""Examine a dataset's episodes: the figures a curator acts on, and flags with their reasons.

    python -m adlpipe.doctor data/adl.h5 [--json doctor.json] [--png doctor.png] [--episodes NAME ...]
    python -m adlpipe.doctor data/adl.h5 --verify data/bags/          # the dataset against its bags

Per episode (adlpipe/curation/doctor.py): frame rate and its largest gap; sync residuals of the end-effector tf,
joint states and depth against the camera frames; tf gaps (and gaps bridged at ingest); idle time at the start and
the end; path length, peak speed and jerk of the end effector; gripper events; repeated (frozen) frames; depth
holes; and outliers against the task's other episodes (robust z-scores). Prints a summary table per task and one
line per flag; --json writes every figure for scripts (what `adlpipe.edit --drop-flagged` reads), --png an
overview. Exit 0 when it ran, flagged or not.

--verify BAGS reads each episode's source bag again (found among BAGS by its sha256) as ingest read it and
compares every stored array and camera attribute with it: one line per mismatch, exit 1 if there is any.
"""

from __future__ import annotations

import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .curation import doctor
from .plumbing.atomic import check_outputs, json_text, write_all_atomic
from .plumbing.cli import Parser, float_range
from .plumbing.errors import AdlError, run_cli

FLAG_KINDS = ("frozen camera", "frame gap", "tf glitch", "tf gap", "idle start", "idle end", "sync", "depth holes",
              "joint spike", "joint flatline", "action frozen", "non-finite values", "gripper chatter",
              "near duplicate", "outlier")


def overview_png(figs: dict[str, dict], path: Path) -> bytes:
    """Per task, each episode's duration against its path length (flagged ones red), and the count of each kind
    of flag."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2), gridspec_kw={"width_ratios": [3, 2]})
    tasks = sorted({f["task"] for f in figs.values()})
    for i, task in enumerate(tasks):
        rows = [f for f in figs.values() if f["task"] == task]
        ok = [r for r in rows if not r["flags"]]
        bad = [r for r in rows if r["flags"]]
        a.scatter([r["duration_s"] for r in ok], [r["path_m"] for r in ok], s=12, color=f"C{i % 10}", label=task)
        a.scatter([r["duration_s"] for r in bad], [r["path_m"] for r in bad], s=30, facecolor="none",
                  edgecolor="red", linewidth=1.2)
    a.set_xlabel("duration (s)")
    a.set_ylabel("end-effector path length (m)")
    a.set_title(f"{len(figs)} episodes; red rings: flagged")
    if len(tasks) <= 12:
        a.legend(fontsize=7, loc="best")
    counts = [sum(any(fl.startswith(k + ":") for fl in f["flags"]) for f in figs.values()) for k in FLAG_KINDS]
    b.barh(np.arange(len(FLAG_KINDS)), counts, color="firebrick")
    b.set_yticks(np.arange(len(FLAG_KINDS)), FLAG_KINDS)
    b.invert_yaxis()
    b.set_xlabel("episodes flagged")
    b.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.doctor", __doc__)
    p.add_argument("data", type=Path, help="dataset index (e.g. data/adl.h5)")
    p.add_argument("--episodes", nargs="+", help="episode names (default: all)")
    p.add_argument("--json", type=Path, help="write every episode's figures and flags here")
    p.add_argument("--png", type=Path, help="write an overview figure here")
    p.add_argument("--idle-s", type=float_range(0, lo_open=True), default=doctor.Limits.idle_s,
                   help="flag idle time at the start or end longer than this (s)")
    p.add_argument("--max-speed", type=float_range(0, lo_open=True), default=doctor.Limits.max_speed_mps,
                   help="an end effector faster than this (m/s) is a tf glitch")
    p.add_argument("--verify", nargs="+", type=Path, metavar="BAGS",
                   help="compare the dataset with its bags (files, folders, split recordings)")
    p.add_argument("--config", type=Path, action="append",
                   help="with --verify: the topic map to read the bags with (default: the one each episode was "
                   "ingested with)")
    p.add_argument("--robot-mjcf", type=Path,
                   help="the robot's MuJoCo model: its forward kinematics from the recorded joints is checked against "
                   "the tf end effector (joint names, order, units); default: not checked")
    p.add_argument("--ee-site", default="tcp", help="with --robot-mjcf: the model's end-effector site (default tcp)")
    p.io(inputs=["data", "verify", "config", "robot_mjcf"], outputs=["json", "png"],
         implied=lambda a: [a.data.with_name("split.json")])  # the split beside it is part of the dataset
    args = p.parse_args(argv)
    outputs = [o for o in (args.json, args.png) if o]
    check_outputs(*outputs)
    if args.verify:
        from .curation.verify import verify

        lines, checked, missing = verify(args.data, args.verify, args.config, args.episodes)
        for line in lines:
            print(line)
        if missing:
            print(f"note: no bag given for {len(missing)} episode(s) (e.g. {missing[0]}); not verified",
                  file=sys.stderr)
        if not checked:
            raise AdlError(f"none of the given bags is the source of an episode of {args.data}")
        print(f"{args.data}: {checked} episode(s) verified against their bags, {len(lines)} mismatch(es)")
        return 1 if lines else 0
    limits = doctor.Limits(idle_s=args.idle_s, max_speed_mps=args.max_speed)
    robot = None
    if args.robot_mjcf:
        from .offline.robot import Robot  # mujoco: the sim extra, needed only here

        robot = Robot(path=args.robot_mjcf, ee_site=args.ee_site)
    figs = doctor.examine(str(args.data), args.episodes, limits, robot)
    print(doctor.summary_table(figs), end="")
    for line in doctor.flag_lines(figs):
        print(line)
    flagged = sum(bool(f["flags"]) for f in figs.values())
    files: dict = {}
    if args.json:
        files[args.json] = json_text({"limits": asdict(limits), "episodes": figs})
    if args.png:
        files[args.png] = overview_png(figs, args.png)
    if files:
        write_all_atomic(files)
    print(f"{args.data}: {len(figs)} episode(s), {flagged} flagged")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.doctor", main))
