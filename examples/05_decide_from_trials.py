"""Decide between two policies from trials on your robot, with the rule the report uses (safety first, then success
within a margin, then latency), checked after every trial: continue (and which policy next) or stop.

    python examples/05_decide_from_trials.py examples/trials.csv
    python examples/05_decide_from_trials.py examples/trials.csv --margin 0.10

The CSV holds a row per trial (policy, success, force_n, ...: docs/guide/decision.md); trial bags written by
`adlpipe replay --trial-bags` or a lab's own logger work as well. `adlpipe trials` is the same as a command.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from adlpipe.evaluation.trials import TrialsConfig, run_trials


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("trials", type=Path, nargs="+")
    p.add_argument("--margin", type=float, default=0.05, help="non-inferiority margin on success (0.05: 5 points)")
    args = p.parse_args()

    said, decision = run_trials(TrialsConfig(inputs=args.trials, margin=args.margin,
                                             latency=["fm_cnn=3.0", "dp_cnn=31.3"]))  # ms, from evaluate
    print("\n".join(said[-6:]))  # the last trials read, then the decision's lines
    print(f"\nstatus {decision['status']}, recommended {decision['recommended']}, next {decision['next']}, "
          f"after {decision['trials']} trials")


if __name__ == "__main__":
    main()
