"""The report's figures as PNG bytes: train and test loss FM vs DP (the seed's Fig. 2), val px vs epoch, px and ms vs
sampling steps."""

from __future__ import annotations

import io
import math
from pathlib import Path


def model_styles(models: list[str]) -> dict[str, dict]:
    """A colour per model (none shared) and a line style per objective family, so no two series look alike."""
    import matplotlib

    colours = matplotlib.colormaps["tab10"].colors
    dash = {"fm": "-", "dp": "--", "bc": ":", "mf": "-."}
    return {m: {"color": colours[i % len(colours)], "linestyle": dash.get(m.split("_")[0], "-")}
            for i, m in enumerate(models)}


def label_steps(ax: object, steps: list[int]) -> None:
    """A log step axis labelled with the step counts themselves (not only 10^0 and 10^1)."""
    from matplotlib.ticker import FixedLocator, NullLocator, ScalarFormatter

    ax.set_xscale("log")
    ax.xaxis.set_major_locator(FixedLocator(sorted(set(steps))))
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_locator(NullLocator())


def figures(ev: dict, read: dict[str, dict[str, list[float]]], out_dir: Path) -> dict[Path, bytes]:
    """The seed's Fig. 2 (train/test loss FM vs DP, one panel each: their losses are of different objectives),
    val px vs epoch, px and ms vs steps (all models on a log axis, and beside it the models within 3x of the best on
    a linear one, so one far-off model does not hide the others' differences), as PNG files. read: each model's
    training log columns (read_training_log)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    made: dict[Path, bytes] = {}
    styles = model_styles(list(ev.get("models", {})) or list(read))

    def save(fig, name: str) -> None:  # noqa: ANN001
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
        plt.close(fig)
        made[out_dir / name] = buf.getvalue()  # written with the report, all or none

    if read:
        pair = [m for m in ("fm_cnn", "dp_cnn") if m in read]
        fig, axes = plt.subplots(1, max(len(pair), 1), figsize=(5.5 * max(len(pair), 1), 4), squeeze=False)
        for ax, m in zip(axes[0], pair, strict=False):
            ax.plot(read[m]["epoch"], read[m]["train_loss"], color=styles.get(m, {}).get("color"), label="train")
            pts = [(e, v) for e, v in zip(read[m]["epoch"], read[m]["test_loss"], strict=False)
                   if not math.isnan(v)]  # measured with each validation
            if pts:
                ax.plot(*zip(*pts, strict=True), "--", color="black", label="test")
            ax.set(xlabel="epoch", ylabel=f"{m} loss (its own objective)", yscale="log", title=m)
            ax.legend()
        fig.suptitle("Train and test loss, FM vs DP (separate axes: different objectives)")
        save(fig, "loss_fm_vs_dp.png")
        fig, ax = plt.subplots(figsize=(6, 4))
        for m, cols in read.items():
            pts = [(e, v) for e, v in zip(cols["epoch"], cols.get("val_px", []), strict=False) if not math.isnan(v)]
            if pts:
                ax.plot(*zip(*pts, strict=True), marker=".", label=m, **styles.get(m, {}))
        ax.set(xlabel="epoch", ylabel="val px (default sampler)", yscale="log", title="Validation error vs epoch")
        ax.legend(fontsize=7)
        save(fig, "val_px_vs_epoch.png")
    for key, ylabel, name in (("px", "px (test, best checkpoint)", "px_vs_steps.png"),
                              ("ms", "ms per sample, batch 1", "ms_vs_steps.png")):
        series: list[tuple[str, str, list]] = []
        for model, by_ck in ev.get("models", {}).items():
            per: dict[str, list] = {}
            for r in by_ck.get("best", {}).values():
                per.setdefault(r["method"], []).append((r["steps"], r[key]))
            series += [(model, method, sorted(pts)) for method, pts in per.items()]
        steps = sorted({s for _m, _k, pts in series for s, _v in pts})
        lowest = min((v for _m, _k, pts in series for _s, v in pts), default=1.0)
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for ax, zoom in zip(axes, (False, True), strict=True):
            for model, method, pts in series:
                if zoom and min(v for _s, v in pts) > 3 * lowest:
                    continue
                style = dict(styles.get(model, {}))
                if len(pts) == 1:  # a regressor: one figure for every step count
                    style["linestyle"] = ":"
                    ax.axhline(pts[0][1], label=model, **style)
                else:
                    ax.plot(*zip(*pts, strict=True), marker="o", label=f"{model} {method}", **style)
            label_steps(ax, steps or [1])
            ax.set(xlabel="sampling steps", ylabel=ylabel, yscale="linear" if zoom else "log",
                   title=f"{key} vs steps" + (" (within 3x of the best, linear)" if zoom else " (all, log)"))
            ax.legend(fontsize=6)
        save(fig, name)
    return made
