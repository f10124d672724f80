"""Train's per-epoch CSV (epoch, step, train loss; test loss and val px on the epochs that validate), read back as
columns for the report's figures and the studies' curves, and the 2 % rule that says whether a run converged (train
writes its verdict into metrics.json; Table 2 applies it to the benchmarks' histories)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from ..plumbing.errors import AdlError

CONVERGENCE_TOLERANCE = 0.02  # best val px may fall by at most 2 % over the last fifth of training


def read_training_log(path: Path) -> dict[str, list[float]]:
    """A training log's columns as numbers (empty cells NaN); a log that is not such a CSV is one line."""
    cols: dict[str, list[float]] = {}
    try:
        with open(path, newline="") as f:
            for r in csv.DictReader(f):
                for k, v in r.items():
                    cols.setdefault(str(k), []).append(float(v) if v not in ("", None, "None") else math.nan)
    except (OSError, UnicodeDecodeError, csv.Error, ValueError, TypeError) as exc:
        raise AdlError(f"{path}: not a training log CSV ({type(exc).__name__}: {str(exc)[:80]})") from None
    if not {"epoch", "train_loss"} <= set(cols):
        raise AdlError(f"{path}: not a training log CSV (no epoch and train_loss columns)")
    return cols


def validated_rows(cols: dict[str, list[float]], keys: tuple[str, ...]) -> dict[str, list[float]]:
    """The columns `keys` at the epochs that carry a validation (test loss and val px both measured)."""
    keep = [i for i, (a, b) in enumerate(zip(cols["test_loss"], cols["val_px"], strict=True))
            if not (math.isnan(a) or math.isnan(b))]
    return {k: [cols[k][i] for i in keep] for k in keys}


def converged(history: list[dict], tolerance: float = CONVERGENCE_TOLERANCE) -> bool:
    """False if the best val px over the whole run is more than `tolerance` below the best of its first 4/5."""
    vals = [(r["epoch"], r["val_px"]) for r in history if r.get("val_px") is not None]
    if len(vals) < 2:
        return False
    cut = 0.8 * history[-1]["epoch"]
    early = [v for e, v in vals if e <= cut]
    return bool(early) and min(v for _, v in vals) >= (1 - tolerance) * min(early)
