"""What evaluate writes from its rows: the paper's Table 1 in markdown, the other cameras' table, the headline
figures for `dvc metrics` and the error / latency vs steps CSV for `dvc plots`."""

from __future__ import annotations

import csv
import io

from ..policy.blind import BLIND
from .accuracy import DEFAULTS, PAPER_IMAGE_PX
from .tables import error_cell, share_cell


def table1(results: dict[str, dict], k: int, training: dict[str, dict]) -> str:
    """One row per model, checkpoint, sampler and step count."""
    any_row = next(r for ck in results.values() for rows in ck.values() for r in rows.values())
    lines = [f"px: pixels of the {any_row['image_px']} px stored image (models see {any_row['input_px']} px), the "
             f"mean over {any_row['n']} test episodes with its 95 % bootstrap interval; px224: px x {PAPER_IMAGE_PX}/"
             f"{any_row['image_px']}, a rescaling to the paper's image size, not a measurement on {PAPER_IMAGE_PX} px "
             "images; cm likewise with its interval. best: the checkpoint with the lowest validation px; last: the "
             f"final one. {BLIND}: the blind baseline, each test episode's task mean training trajectory (it ignores "
             "the image): the floor a model's learning is measured against.", "",
             "| method | checkpoint (epoch) | converged | sampler | steps | px [95 %] | px224 | cm [95 %] | "
             f"ms [95 %] | best-of-{k} px [95 %] | "
             "px (multimodal tasks) [95 %] | mode commitment [95 %] |",
             "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for model, by_ck in results.items():
        conv = {True: "yes", False: "**no**", None: "?"}[training.get(model, {}).get("converged")]
        if model == BLIND:
            conv = "- (not trained)"
        for ck, rows in by_ck.items():
            if model == BLIND and ck == "last":
                continue  # one set of task means: no checkpoints
            for r in rows.values():
                mm = error_cell(r, "px_multimodal") if r["px_multimodal"] is not None else "-"
                lines.append(f"| {model} | {ck} ({r['epoch']}) | {conv} | {r['method']} | {r['steps']} | "
                             f"{error_cell(r, 'px')} | {r['px224']:.2f} | {error_cell(r, 'cm')} | "
                             f"{error_cell(r, 'ms', 1)} | "
                             f"{error_cell(r, f'best_of_{k}_px')} | {mm} | {share_cell(r, 'commitment')} |")
    return "\n".join(lines) + "\n" + camera_table(results)


def camera_table(results: dict[str, dict]) -> str:
    """px in each other camera of the episodes (the predicted 3D waypoints seen through it), best checkpoints'
    rows; empty for one-camera data."""
    rows = [(model, r) for model, by_ck in results.items() for r in by_ck["best"].values() if r.get("px_by_camera")]
    if not rows:
        return ""
    names = sorted(rows[0][1]["px_by_camera"])
    lines = ["", "px in the other cameras (the predicted 3D waypoints as each camera saw the scene at the first "
             "image, against the demonstration in that camera; best checkpoints):", "",
             "| method | sampler | steps | " + " | ".join(f"{c} px [95 %]" for c in names) + " |",
             "| --- | --- | ---: |" + " ---: |" * len(names)]
    for model, r in rows:
        cells = " | ".join(error_cell(r["px_by_camera"][c], "px") for c in names)
        lines.append(f"| {model} | {r['method']} | {r['steps']} | {cells} |")
    return "\n".join(lines) + "\n"


def headline(results: dict[str, dict], training: dict[str, dict], n_test: int) -> dict:
    """The few numbers `dvc metrics show` prints: per model, its best checkpoint with its default sampler and step
    count (FM 1, DP 16, BC direct; px_16_steps for FM), and whether it converged."""
    out: dict = {"n_test": n_test}
    for model, by_ck in results.items():
        best = by_ck["best"]
        default = best.get(DEFAULTS.get(model, "")) or min(best.values(), key=lambda r: r["steps"])
        h = {"px": round(default["px"], 3), "px224": round(default["px224"], 3), "ms": round(default["ms"], 2),
             "cm": round(default["cm"], 3),
             "converged": training.get(model, {}).get("converged"),
             "val_px_best": training.get(model, {}).get("val_px_best"),
             "commitment": None if default.get("commitment") is None else round(default["commitment"], 3)}
        r16 = best.get(f"{default['method']}/16")
        if r16 is not None and default["steps"] != 16:
            h["px_16_steps"] = round(r16["px"], 3)
        out[model] = h
    return out


def steps_csv(results: dict[str, dict], steps_list: list[int]) -> str:
    """Wide CSV for `dvc plots`: one row per step count, columns <model>_<sampler>_{px,cm,ms}, of the best
    checkpoints (as the report's figures). A regressor does not depend on steps: its single figure is repeated as a
    flat reference line."""
    series: dict[str, dict[int, dict]] = {}
    for model, by_ck in results.items():
        for r in by_ck["best"].values():
            series.setdefault(f"{model}_{r['method']}", {})[r["steps"]] = r
    cols = [f"{name}_{m}" for name in series for m in ("px", "cm", "ms")]
    f = io.StringIO()
    w = csv.writer(f, lineterminator="\n")
    w.writerow(["steps", *cols])
    for k in steps_list:
        row = [k]
        for by_steps in series.values():
            r = by_steps.get(k) or by_steps[min(by_steps)]
            row += [f"{r['px']:.4f}", f"{r['cm']:.4f}", f"{r['ms']:.3f}"]
        w.writerow(row)
    return f.getvalue()
