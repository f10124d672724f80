"""README's Table 2: the state benchmarks' longest runs, the final checkpoint beside the best ones (written by
`python -m adlpipe.results` from the benchmark pipelines' committed results)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from ..plumbing.errors import AdlError
from .stats import interval_cell
from .training_log import converged, read_training_log

# (benchmark, its pipeline's results folder under pipelines/, the details file there, model, label, demonstrations)
RUNS = (
    ("Push-T", "pusht_levers/results", "pusht_levers_long_details.json", "fm_cnn_d1000_e18", "FM-CNN", 1000),
    ("Push-T", "pusht_levers/results", "pusht_levers_long_details.json", "dp_cnn_d1000_e18", "DP-CNN (sample)", 1000),
    ("Franka Kitchen", "kitchen_levers/results", "kitchen_long_details.json", "fm_cnn_e30", "FM-CNN", 560),
    ("Franka Kitchen", "kitchen_levers/results", "kitchen_long_details.json", "dp_cnn_e30", "DP-CNN (sample)", 560),
    ("Franka Kitchen", "kitchen_levers/results", "kitchen_e60_details.json", "fm_cnn_e60", "FM-CNN", 560),
    ("Franka Kitchen", "kitchen_levers/results", "kitchen_e60_details.json", "dp_cnn_e60", "DP-CNN (sample)", 560),
)
HEAD = ("| benchmark | policy | demos | optimiser steps | final checkpoint: score [95 %] at 16 steps (2 steps) | "
        "success at 16 | best-validation checkpoint, 16 steps | along training, 16 steps: best checkpoint (at step) / "
        "last 3 | converged (2 % rule) |")


def _details(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise AdlError(f"{path}: not a benchmark details file ({type(exc).__name__}: {exc})") from None


def _result(details: dict, model: str, steps: int, checkpoint: str) -> dict | None:
    return next((r for r in details.get("results", []) if (r["model"], r["steps"], r.get("checkpoint", "last"))
                 == (model, steps, checkpoint)), None)


def _training(log: Path) -> tuple[str, str]:
    """(optimiser steps, converged) from the run's committed per-epoch log; '-' without it."""
    if not log.is_file():
        return "-", "-"
    cols = read_training_log(log)
    history = [{"epoch": e, "val_px": None if math.isnan(v) else v}  # epochs without validation: NaN
               for e, v in zip(cols["epoch"], cols["val_px"], strict=True)]
    return f"{int(cols['step'][-1]):,}", "yes" if converged(history) else "no"


def row(pipelines: Path, run: tuple) -> str | None:
    """One model's row, or None while its details file is not committed."""
    bench, folder, name, model, label, demos = run
    path = pipelines / folder / name
    if not path.is_file():
        return None
    details = _details(path)
    last16, last2, best16 = (_result(details, model, s, c) for s, c in ((16, "last"), (2, "last"), (16, "best")))
    if last16 is None:
        raise AdlError(f"{path}: no 16-step result of the final checkpoint of {model}")
    curve = next((c for c in details.get("curves", []) if c["model"] == model and c["steps"] == 16), None)
    along = "-" if curve is None else (
        f"{curve['max']['score']:.3f} ({curve['max']['step']:,}) / {curve['last']['score']:.3f} "
        f"({curve['episodes']} initial conditions each)")
    steps, ok = _training(pipelines / folder / "train" / f"{model}.csv")
    final = f"**{interval_cell(last16['score'], last16['score_ci'])}**" + (
        f" ({last2['score']:.3f})" if last2 else "") + f", {last16['n']} initial conditions"
    best = "not run" if best16 is None else interval_cell(best16["score"], best16["score_ci"])
    return (f"| {bench} | {label} | {demos:,} | {steps} | {final} | {100 * last16['success']:.0f} % | {best} | "
            f"{along} | {ok} |")


def table2_lines(pipelines: Path) -> list[str]:
    """The table's lines; none when no benchmark pipeline has committed its results."""
    rows = [r for r in (row(pipelines, run) for run in RUNS) if r is not None]
    return [HEAD, "|" + " --- |" * (HEAD.count("|") - 1), *rows] if rows else []
