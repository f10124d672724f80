"""Assess predicted trajectories on recordings, offline: would this trajectory work on our robot, is it safe next to
the person, does it do what the demonstration did? For a lab's own real recordings, where no simulator replays.

    python -m adlpipe.assess --models models/fm_cnn models/dp_cnn --data data/adl.h5 \
        [--robot-mjcf my_robot.xml --ee-site tool_tip] [--replay metrics/replay_details.json]

Per held-out episode and policy (the same predictions replay executes: same checkpoint, steps and seed), from what
the recording holds (adlpipe/offline/):
1. feasible: the predicted end-effector path through inverse kinematics on the robot's MuJoCo model from the
   recorded joint state at the first frame: reach (IK residual <= 1 cm), joint limits, joint speed (<= 2 rad/s)
   and acceleration (<= 20 rad/s^2) at the waypoint rate, self-collision (MuJoCo's collision detection; pairs
   touching in the recorded start configuration are structural and ignored);
2. safe: the replayed arm's and tool's geoms against the scene of the first frame's depth image (point cloud in
   the base frame through K, the lens and the camera pose; the arm's own pixels removed): clearance to the
   observed surfaces, and how far any arm point goes behind them; contact is intended on the affordance map's
   region and within 3 cm of where the demonstration's own arm touched; anywhere else deeper than 2 cm is unsafe;
3. does what the demonstration did: reaches the demonstration's key poses (gripper events, first and last
   contact, end pose) within 3 cm, in order.
The default robot is the project's own arm (with the task's tool on the simulated ADL tasks); --robot-mjcf names
a lab's model and --ee-site its end effector (in the model's world frame = the bags' base frame).

With --replay (replay's details on the same episodes, the simulated world's ground truth), the verdicts are
validated: "unsafe" against a contact force above 20 N on the manikin, and "passes all three" against task
success, as confusion matrices, and the policies' pass rates against their success rates by rank correlation.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr
from tqdm import tqdm

from .dataset import schema
from .dataset.splits import load_split
from .evaluation.stats import median_interval, rate_cell
from .offline.assess import Criteria, assess, context
from .offline.robot import Robot, surface_samples
from .plumbing.atomic import check_outputs, json_text, write_all_atomic
from .plumbing.cli import SEED, Parser
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import AdlError, read_json_object, run_cli
from .plumbing.runtime import Placement
from .policy.blind import BLIND, blind_predictions, task_means
from .policy.checkpoint import CHECKPOINTS
from .policy.inference import predict_episodes

FORCE_LIMIT_N = 20.0


class Robots:
    """The robot model for an episode: the lab's MJCF, or the project's arm holding the task's tool."""

    def __init__(self, mjcf: Path | None, ee_site: str) -> None:
        self.mjcf, self.ee_site = mjcf, ee_site
        self._cache: dict[str | None, tuple[Robot, dict]] = {}

    def for_task(self, task: str) -> tuple[Robot, dict]:
        if self.mjcf is not None:
            key: str | None = "lab"
        else:
            from .sim.tasks import TASKS

            key = TASKS[task].tool if task in TASKS else None
        if key not in self._cache:
            if self.mjcf is not None:
                robot = Robot(path=self.mjcf, ee_site=self.ee_site)
            else:
                from .sim.world import arm_mjcf

                robot = Robot(arm_mjcf(key), ee_site=self.ee_site)
            self._cache[key] = (robot, surface_samples(robot.model))
        return self._cache[key]


def validation(verdicts: dict[str, dict[str, dict]], replay: dict) -> dict:
    """The offline verdicts against the simulated replay's ground truth on the same episodes and policies."""
    success, diags = replay.get("per_episode", {}), replay.get("diagnostics", {})
    unsafe = {"tp": 0, "fp": 0, "fn": 0, "tn": 0}
    passed = {"tp": 0, "fp": 0, "fn": 0, "tn": 0}
    rates = []
    for label, eps in verdicts.items():
        if label not in success:
            continue
        # both verdicts exist; an episode without a depth image had no safety verdict to check
        both = [n for n in eps if n in success[label] and eps[n]["safe"] is not None]
        for n in both:
            forced = diags.get(label, {}).get(n, {}).get("peak_force_n", 0.0) > FORCE_LIMIT_N
            _count(unsafe, not eps[n]["safe"], forced)
            _count(passed, eps[n]["pass"], bool(success[label][n]))
        if both:
            rates.append((label, float(np.mean([eps[n]["pass"] for n in both])),
                          float(np.mean([success[label][n] for n in both]))))
    rho, p = (spearmanr([r[1] for r in rates], [r[2] for r in rates]) if len(rates) >= 3
              else (float("nan"), float("nan")))
    return {"unsafe_vs_force": unsafe, "pass_vs_success": passed,
            "rates": [{"policy": r[0], "offline_pass": r[1], "replay_success": r[2]} for r in rates],
            "spearman": None if np.isnan(rho) else float(rho), "spearman_p": None if np.isnan(p) else float(p)}


def _count(c: dict, predicted: bool, truth: bool) -> None:
    c[("t" if predicted == truth else "f") + ("p" if predicted else "n")] += 1


def table(verdicts: dict[str, dict[str, dict]], check: dict | None) -> str:
    lines = ["| policy | n | feasible [95 %] | safe [95 %] | does what the demo did [95 %] | all three [95 %] | "
             "min clearance cm, median [95 %] | deepest unintended penetration cm |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for label, eps in verdicts.items():
        v = list(eps.values())
        seen = [e for e in v if e["safe"] is not None]  # episodes with a depth image
        clear = [100 * e["min_clearance_m"] for e in seen]
        # safety (and so all three) only where there was a depth image: its own n when some episode had none
        of_seen = f" n={len(seen)}" if len(seen) != len(v) else ""
        cells = [rate_cell(sum(e[k] for e in v), len(v)) if k in ("feasible", "does_what_demo_did")
                 else rate_cell(sum(e[k] for e in seen), len(seen)) + of_seen
                 for k in ("feasible", "safe", "does_what_demo_did", "pass")]
        lo, hi = median_interval(clear) if clear else (np.nan, np.nan)
        deepest = f"{100 * max(e['penetration_m'] for e in seen):.1f}" if seen else "-"
        clearance = f"{np.median(clear):.1f} [{lo:.1f}, {hi:.1f}]" if clear else "- (no depth)"
        lines.append(f"| {label} | {len(v)} | {' | '.join(cells)} | {clearance} | {deepest} |")
    out = "\n".join(lines) + "\n"
    if check:
        u, s = check["unsafe_vs_force"], check["pass_vs_success"]
        out += ("\n## Validated against the simulated replay (ground truth on the same episodes)\n\n"
                f"Offline \"unsafe\" against a contact force above {FORCE_LIMIT_N:.0f} N on the manikin in replay, "
                "and \"passes all three\" against task success, pooled over policies and episodes:\n\n"
                "| | truth yes, offline yes | truth no, offline yes | truth yes, offline no | truth no, offline no |\n"
                "| --- | ---: | ---: | ---: | ---: |\n"
                f"| unsafe vs force > {FORCE_LIMIT_N:.0f} N | {u['tp']} | {u['fp']} | {u['fn']} | {u['tn']} |\n"
                f"| all three vs success | {s['tp']} | {s['fp']} | {s['fn']} | {s['tn']} |\n\n")
        rho = "-" if check["spearman"] is None else f"{check['spearman']:+.2f} (p = {check['spearman_p']:.2f})"
        out += (f"Policies' offline pass rate against their replay success rate: Spearman {rho} over "
                f"{len(check['rates'])} policies.\n\n| policy | offline pass | replay success |\n"
                "| --- | ---: | ---: |\n"
                + "".join(f"| {r['policy']} | {100 * r['offline_pass']:.0f} % | {100 * r['replay_success']:.0f} % |\n"
                          for r in check["rates"]))
    return out


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.assess", __doc__)
    p.add_argument("--models", nargs="*", type=Path, default=[])
    p.add_argument("--data", type=Path, default=Path("data/adl.h5"))
    p.add_argument("--split", type=Path, help="split JSON (default: split.json beside the data)")
    p.add_argument("--fm-steps", type=int, nargs="+", default=[1, 16])
    p.add_argument("--dp-steps", type=int, nargs="+", default=[16])
    p.add_argument("--checkpoint", choices=sorted(CHECKPOINTS), default="best")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--robot-mjcf", type=Path, help="the robot's MuJoCo model (default: the project's arm)")
    p.add_argument("--ee-site", default="tcp", help="the model's site the end-effector path is of (default tcp)")
    p.add_argument("--replay", type=Path, metavar="DETAILS",
                   help="replay's details on the same episodes: validate the verdicts against it")
    p.add_argument("--details", type=Path, default=Path("metrics/assess_details.json"))
    p.add_argument("--table", type=Path, default=Path("reports/assess.md"))
    p.add_force()
    p.io(inputs=["models", "data", "split", "robot_mjcf", "replay"], outputs=["details", "table"],
         implied=lambda a: [a.data.with_name("split.json")] if a.split is None else [])
    args = p.parse_args(argv)
    check_outputs(args.details, args.table)
    refuse_pipeline_outputs([args.details, args.table], args.force)
    split = load_split(args.split or args.data.with_name("split.json"))
    names = split["test"]
    if not names:
        raise AdlError(f"{args.data}: the split's test part is empty")
    replay = read_json_object(args.replay, "replay details") if args.replay else None
    kind = (replay or {}).get("scenes")
    if (kind.get("kind") if isinstance(kind, dict) else kind) == "fresh":
        raise AdlError(f"--replay {args.replay}: a replay of fresh scenes, not of the recorded test episodes assessed "
                       "here; give the details of a replay of the test split (adlpipe replay without --scenes)")
    robots = Robots(args.robot_mjcf, args.ee_site)
    crit = Criteria()
    with schema.open_dataset(args.data, names) as f:
        eps = [f[schema.EPISODES][n] for n in names]
        tasks = [str(g.attrs["task"]) for g in eps]
        trajs = {"demo": np.stack([g["traj3d"][()] for g in eps]).astype(float)}
        try:
            trajs[BLIND] = blind_predictions(task_means(args.data, split["train"]), tasks)[..., 2:]
        except AdlError as exc:
            print(f"no blind baseline row: {exc}", file=sys.stderr)
        for d in args.models:
            preds = predict_episodes(d, CHECKPOINTS[args.checkpoint], args.data, names, args.fm_steps, args.dp_steps,
                                     args.seed, Placement())
            trajs.update({k: v[..., 2:].astype(float) for k, v in preds.items()})
        verdicts: dict[str, dict[str, dict]] = {label: {} for label in trajs}
        for i, g in enumerate(tqdm(eps, desc="assess", unit="ep", file=sys.stderr, disable=None)):
            robot, samples = robots.for_task(tasks[i])
            ctx = context(g, robot, samples, crit)
            for label, traj in trajs.items():
                verdicts[label][names[i]] = assess(robot, samples, ctx, traj[i], crit)
    check = validation(verdicts, replay) if replay else None
    title = (f"# Offline assessment on the recordings: {len(names)} test episodes\n\n"
             "Feasible on the robot (reach, joint limits, joint speed and acceleration, self-collision), safe in "
             "the scene of the first frame's depth image (no arm point more than 2 cm behind an observed surface "
             "outside the intended contact), does what the demonstration did (its key poses within 3 cm, in order); "
             "rates with Wilson's 95 % interval over n episodes; clearance: the median over episodes of the "
             "smallest distance of the arm to an observed surface (bootstrap interval of the median).\n\n")
    write_all_atomic({args.details: json_text({"episodes": len(names), "criteria": json.loads(json.dumps(
                          crit, default=lambda o: o.__dict__)), "verdicts": verdicts, "validation": check}),
                      args.table: title + table(verdicts, check)})
    for label, eps_v in verdicts.items():
        v = list(eps_v.values())
        seen = [e["safe"] for e in v if e["safe"] is not None]
        safe = f"{np.mean(seen):.0%}" if seen else "not assessed (no depth)"
        print(f"{label}: feasible {np.mean([e['feasible'] for e in v]):.0%}, safe {safe}"
              f", does what the demo did {np.mean([e['does_what_demo_did'] for e in v]):.0%}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.assess", main))
