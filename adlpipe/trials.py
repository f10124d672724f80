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

import argparse
import math
import sys
from pathlib import Path

from .evaluation.decision import Rule, policies_of
from .evaluation.trials import TrialSeries, read_trials
from .plumbing.atomic import check_outputs, json_text, write_all_atomic
from .plumbing.cli import Parser, float_range
from .plumbing.errors import AdlError, read_json_object, run_cli


def latencies(args: argparse.Namespace) -> dict[str, float | None]:
    out: dict[str, float | None] = dict(policies_of(read_json_object(args.eval, "evaluate details", "models"))
                                        if args.eval else {})
    for item in args.latency or []:
        name, _, ms = item.partition("=")
        try:
            value = float(ms)
        except ValueError:
            raise AdlError(f"--latency {item!r}: expected POLICY=MS, e.g. fm_cnn=3.5") from None
        if not name.strip() or not math.isfinite(value) or value < 0:
            raise AdlError(f"--latency {item!r}: expected POLICY=MS with a policy name and a finite ms >= 0")
        out[name.strip()] = value
    return out


def check_names(args: argparse.Namespace, trials: list, latency: dict[str, float | None]) -> None:
    """--policies without empty names, --latency only for policies under trial."""
    if args.policies and not all(p.strip() for p in args.policies):
        raise AdlError("--policies: an empty policy name")
    known = set(args.policies or []) | {t.policy for t in trials}
    unknown = [p for p in (item.partition("=")[0].strip() for item in args.latency or []) if p not in known]
    if unknown:
        raise AdlError(f"--latency {unknown[0]}: no such policy among the trials ({', '.join(sorted(known))})")


def main(argv: list[str] | None = None) -> int:
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
    trials = read_trials(args.inputs)
    if not trials:
        raise AdlError(f"{', '.join(map(str, args.inputs))}: no trials")
    latency, rule = latencies(args), Rule(args.margin, args.alpha)
    check_names(args, trials, latency)
    decision: dict = {}
    nxt: str | None = None
    series = TrialSeries(latency, rule, args.policies)  # updated trial by trial: linear in the trials
    for i, t in enumerate(trials, start=1):
        series.add(t)
        decision, nxt = series.decision()
        what = (f"stop: {decision['recommended']}" if nxt is None else f"continue: run {nxt} next")
        print(f"trial {i} ({t.policy}: {'success' if t.success else 'failure'}"
              + (f", {t.force_n:.1f} N" if t.force_n is not None else "") + f"): {what}")
        if nxt is None:
            if i < len(trials):
                print(f"decided after trial {i}; the {len(trials) - i} later trial(s) are not needed for it")
            break
    print("\n".join(decision["lines"]))
    if args.output is not None:
        write_all_atomic({args.output: json_text({**{k: v for k, v in decision.items() if k != "lines"},
                                                  "next": nxt, "trials": len(trials)})})
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.trials", main))
