"""Decide between policies from trials on your own robot, after every trial: continue (and which policy next), or
stop with the decision.

    python -m adlpipe.trials trials.csv                         # policy,success[,trial,force_n,progress] per row
    python -m adlpipe.trials bags/trial_*.mcap --eval metrics/eval_details.json
    python -m adlpipe.trials trials.csv --policies fm_cnn dp_cnn --latency fm_cnn=3.5 dp_cnn=31

The rule is the report's and replay --until-decided's (adlpipe.evaluation.decision): safety first (a trial whose
peak force on the person exceeded 20 N is unsafe), then success with a --margin non-inferiority margin, then
latency; the tests are anytime-valid (testing by betting, adlpipe.evaluation.sequential), so looking after every
trial and stopping at the first decision keeps the error rate at --alpha. Each policy's k-th trial is paired with
the others' k-th: run them alternating, as the suggested next policy does. Trials come from CSVs or from trial bags
(the outcome on /adl/outcome; adlpipe.evaluation.trials says how). A trial bag is an ordinary recording besides:
`python -m adlpipe.ingest` keeps all its frames, so a failed trial can be inspected and assessed like any other.
"""

from __future__ import annotations

import sys
from pathlib import Path

from .evaluation.trials import TrialsConfig, run_trials
from .plumbing.atomic import check_outputs, json_text, write_all_atomic
from .plumbing.cli import Parser, config_from, float_range
from .plumbing.errors import run_cli


def parse_args(argv: list[str] | None) -> tuple[TrialsConfig, Path | None]:
    """The options as the decision's configuration, and where the decision goes as JSON (checked writable)."""
    p = Parser("python -m adlpipe.trials", __doc__)
    p.add_argument("inputs", type=Path, nargs="+", help="trials CSVs and/or trial bags")
    p.add_argument("--policies", nargs="+", help="the policies under trial (default: those the trials name); one "
                   "without trials yet is suggested first")
    p.add_argument("--eval", type=Path, help="evaluate's details: each policy's latency (default sampler)")
    p.add_argument("--latency", nargs="+", metavar="POLICY=MS", help="latencies in ms (over --eval's)")
    p.add_argument("--margin", type=float_range(0.0, 0.5), default=0.05,
                   help="non-inferiority margin on success, as a fraction (default 0.05: 5 points)")
    p.add_argument("--alpha", type=float_range(0.001, 0.5), default=0.05,
                   help="family-wise error rate per step of the rule (default 0.05)")
    p.add_argument("-o", "--output", type=Path, help="the decision as JSON (optional)")
    p.io(inputs=["inputs", "eval"], outputs=["output"])
    args = p.parse_args(argv)
    if args.output is not None:
        check_outputs(args.output)
    return config_from(args, TrialsConfig, eval_details=args.eval), args.output


def main(argv: list[str] | None = None) -> int:
    c, output = parse_args(argv)
    said, decision = run_trials(c)
    print("\n".join(said))
    if output is not None:
        write_all_atomic({output: json_text(decision)})
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.trials", main))
