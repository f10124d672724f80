"""Evaluate trained policies and let fresh simulated scenes decide between them: trajectory error and latency on the
test split, then replay in the MuJoCo ADL world batch by batch until the anytime-valid rule decides (or a cap).

    python examples/04_evaluate_and_decide.py runs/mine/robot.h5 runs/mine/fm_cnn runs/mine/bc_cnn --scenes 20

The rule: safety first, success within a 5-point margin, then latency (docs/guide/decision.md). Replay rebuilds
scenes of the ADL world, so the dataset must be of its tasks (recorded with `adlpipe record`); on a lab's own
robot, trials decide instead (examples/05_decide_from_trials.py). The same as commands: `adlpipe evaluate`,
`adlpipe replay --until-decided`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from adlpipe.evaluation.evaluate_run import EvaluateConfig, run_evaluation
from adlpipe.evaluation.replay_run import ReplayConfig, run_replay


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=Path)
    p.add_argument("models", type=Path, nargs="+")
    p.add_argument("--scenes", type=int, default=20, help="the cap: fresh scenes per task")
    p.add_argument("--batch", type=int, default=5, help="fresh scenes per task between two looks")
    p.add_argument("--out", type=Path, default=Path("decision"))
    args = p.parse_args()

    split, out = args.data.with_name("split.json"), args.out
    ev = EvaluateConfig(models=args.models, data=args.data, split=split, metrics=out / "eval.json",
                        details=out / "eval_details.json", plots=out / "steps.csv", table=out / "table1.md",
                        steps=[1, 16], repeats=5)
    run_evaluation(ev)
    result = run_replay(ReplayConfig(models=args.models, data=args.data, split=split, metrics=out / "replay.json",
                                     details=out / "replay_details.json", table=out / "table2.md",
                                     placement=ev.placement, fm_steps=[1], dp_steps=[16], scenes=args.scenes,
                                     batch=args.batch, until_decided=True, eval_details=ev.details))
    for label, r in result.items():
        print(f"{label}: success {100 * r['overall']:.0f} % over {r['n']} scenes")
    sequential = json.loads((out / "replay_details.json").read_text())["sequential"]
    last = sequential["looks"][-1]
    print(f"{sequential['reason']}: {last['status']}, recommended {last['recommended']}")


if __name__ == "__main__":
    main()
