"""Training seeds as part of the comparison: the same models trained with K seeds on the same data, each evaluated
and replayed on the same test episodes, summarised over the seeds.

    python -m adlpipe.seeds --eval s0/eval_details.json s1/eval_details.json ... \
        --replay s0/replay_details.json s1/replay_details.json ... -o reports/seeds.md --metrics metrics/seeds.json

Per model (its default sampler, best checkpoint): px, cm and open-loop success of every seed, their mean and
standard deviation over the seeds (the spread training randomness alone causes), and how many seeds converged.
Claims over seeds: each claim of the report decided per seed (paired bootstrap over test episodes, as the report)
and once over all seeds, on each test episode's error averaged over the seeds (the episodes stay the unit the
interval is over; the seeds' noise is averaged into each). `pipelines/seeds/` trains and evaluates the seeds.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from .evaluation.stats import paired_difference
from .evaluation.tables import default_row, replay_label, seeds_lines
from .plumbing.atomic import check_outputs, json_text, write_all_atomic
from .plumbing.cli import Parser
from .plumbing.dvc_outputs import refuse_pipeline_outputs
from .plumbing.errors import AdlError, read_json_object, run_cli

# (claim, first model, its row, second model, its row, scale): "first's px below scale x second's"
CLAIMS = (
    ("FM-1 within 10 % of DP-16 (clean-trajectory pair)", "fm_cnn", "euler/1", "dp_cnn", "ddpm/16", 1.1),
    ("FM-16 more accurate than DP-16 (clean-trajectory pair)", "fm_cnn", "euler/16", "dp_cnn", "ddpm/16", 1.0),
    ("FM-1 more accurate than BC (same U-Net)", "fm_cnn", "euler/1", "bc_cnn", "direct/1", 1.0),
    ("FM-1 within 10 % of DP-16 (the paper's pair)", "fm_cnn_velocity", "euler/1", "dp_cnn_epsilon", "ddpm/16", 1.1),
    ("FM-16 more accurate than DP-16 (the paper's pair)", "fm_cnn_velocity", "euler/16", "dp_cnn_epsilon", "ddpm/16",
     1.0),
)


def summarise(evals: list[dict], replays: list[dict]) -> dict:
    """Per model: per-seed px, cm, success and convergence at its default row, with mean and sd over the seeds;
    per claim: per-seed verdicts and the verdict over seeds."""
    tests = [e.get("n_test") for e in evals]
    if len(set(tests)) != 1:
        raise AdlError(f"the seeds were evaluated on different test splits (n_test {tests})")
    models = [m for m in evals[0]["models"] if all(m in e["models"] for e in evals)]
    out: dict = {"seeds": len(evals), "n_test": tests[0], "models": {}, "claims": []}
    for m in models:
        first = default_row(evals[0], m)
        key = f"{first['method']}/{first['steps']}"
        rows = [e["models"][m]["best"][key] for e in evals]
        succ = [r.get("success", {}).get(replay_label(m, rows[0]), {}).get("overall") for r in replays]
        entry = {"row": key, "px": [r["px"] for r in rows], "cm": [r["cm"] for r in rows],
                 "success": succ if None not in succ else None,
                 "converged": [e.get("training", {}).get(m, {}).get("converged") for e in evals]}
        for k in ("px", "cm", "success"):
            v = entry[k]
            if v is not None:
                entry[f"{k}_mean"] = float(np.mean(v))
                entry[f"{k}_sd"] = float(np.std(v, ddof=1)) if len(v) > 1 else 0.0
        out["models"][m] = entry
    for claim, a, ra, b, rb, scale in CLAIMS:
        pairs = [(e["models"].get(a, {}).get("best", {}).get(ra), e["models"].get(b, {}).get("best", {}).get(rb))
                 for e in evals]
        if any(x is None or y is None or not x.get("px_per_episode") for x, y in pairs):
            continue
        per_seed = [paired_difference(x["px_per_episode"], y["px_per_episode"], scale) for x, y in pairs]
        pooled = paired_difference(np.mean([x["px_per_episode"] for x, _ in pairs], 0),
                                   np.mean([y["px_per_episode"] for _, y in pairs], 0), scale)
        out["claims"].append({"claim": claim, "per_seed": [d.verdict().split(" (")[0] for d in per_seed],
                              "per_seed_mean": [round(d.mean, 3) for d in per_seed],
                              "over_seeds": pooled.verdict(), "difference": [pooled.mean, pooled.low, pooled.high]})
    return out


def markdown(s: dict) -> str:
    return "\n".join([f"# Over {s['seeds']} training seeds (the same data, split and budget; {s['n_test']} test "
                      "episodes)", "", *seeds_lines(s)]) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = Parser("python -m adlpipe.seeds", __doc__)
    p.add_argument("--eval", type=Path, nargs="+", required=True, help="evaluate's details, one per seed")
    p.add_argument("--replay", type=Path, nargs="+", required=True, help="replay's details, one per seed (same order)")
    p.add_argument("-o", "--output", type=Path, default=Path("reports/seeds.md"))
    p.add_argument("--metrics", type=Path, default=Path("metrics/seeds.json"))
    p.add_force()
    p.io(inputs=["eval", "replay"], outputs=["output", "metrics"])
    args = p.parse_args(argv)
    if len(args.eval) != len(args.replay):
        raise AdlError(f"--eval names {len(args.eval)} seeds, --replay {len(args.replay)}: give one of each per seed")
    check_outputs(args.output, args.metrics)
    refuse_pipeline_outputs([args.output, args.metrics], args.force)
    evals = [read_json_object(f, "evaluate's details", "models") for f in args.eval]
    s = summarise(evals, [read_json_object(f, "replay's details", "success") for f in args.replay])
    write_all_atomic({args.output: markdown(s), args.metrics: json_text(s)})
    print(markdown(s))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli("adlpipe.seeds", main))
