"""The statistics the tables print: Wilson intervals and McNemar's exact test, against known answers."""

from __future__ import annotations

import pytest

from adlpipe.evaluation.stats import paired_success, rate_cell, success_interval


def test_wilson_interval_of_a_success_rate() -> None:
    lo, hi = success_interval(11, 40)  # 27.5 %: Wilson 95 % is 16.1-42.8 %
    assert lo == pytest.approx(0.1606, abs=5e-4) and hi == pytest.approx(0.4284, abs=5e-4)
    assert success_interval(0, 40)[0] == 0.0 and success_interval(0, 40)[1] == pytest.approx(0.0876, abs=5e-4)
    assert success_interval(20, 20)[1] == pytest.approx(1.0) and success_interval(0, 0) == (0.0, 1.0)
    assert rate_cell(11, 40) == "28 [16, 43]"


def test_mcnemar_counts_only_the_discordant_scenes() -> None:
    a = [True] * 5 + [False] * 30 + [True, True, True, False]
    b = [True] * 5 + [False] * 30 + [False, False, False, True]
    r = paired_success(a, b)
    assert (r.only_first, r.only_second) == (3, 1)
    assert r.p_value == pytest.approx(0.625)  # two-sided exact binomial of 3 in 4 at 1/2
    clear = paired_success([True] * 9 + [False] * 31, [False] * 40)
    assert clear.p_value == pytest.approx(2 / 2**9)  # 9 : 0 is resolved at 5 %
    assert paired_success([True, False], [True, False]).p_value == 1.0  # no discordant scene: nothing to decide
    with pytest.raises(ValueError, match="different lengths"):
        paired_success([True], [True, False])


def test_bootstrap_interval_of_a_mean() -> None:
    """The percentile bootstrap of a mean agrees with the normal approximation on a large sample, is reproducible,
    and collapses to the value when nothing varies."""
    import numpy as np

    from adlpipe.evaluation.stats import mean_cell, mean_interval

    x = np.random.default_rng(4).normal(2.0, 1.0, 400)
    lo, hi = mean_interval(x)
    half = 1.96 * x.std(ddof=1) / np.sqrt(len(x))  # ~0.098
    assert lo == pytest.approx(x.mean() - half, abs=0.02) and hi == pytest.approx(x.mean() + half, abs=0.02)
    assert mean_interval(x) == (lo, hi)  # seeded: a table re-made from the same episodes prints the same interval
    assert mean_interval([0.5, 0.5, 0.5]) == (0.5, 0.5) and mean_interval([0.7]) == (0.7, 0.7)
    assert mean_cell([0.0, 1.0] * 50) == "0.500 [0.400, 0.600]"


def test_median_interval_of_repeated_timings() -> None:
    """Latency is the median of repeated runs; its interval covers the median, shrinks with more repeats and
    collapses when every run took the same time."""
    import numpy as np

    from adlpipe.evaluation.stats import median_interval

    rng = np.random.default_rng(1)
    few, many = rng.gamma(20, 0.5, 10), rng.gamma(20, 0.5, 400)  # ~10 ms with a right tail, as timings have
    lo, hi = median_interval(few)
    assert lo <= np.median(few) <= hi
    lo2, hi2 = median_interval(many)
    assert lo2 <= np.median(many) <= hi2 and hi2 - lo2 < hi - lo
    assert median_interval([4.0, 4.0, 4.0]) == (4.0, 4.0)


def test_ratio_interval_resamples_clusters() -> None:
    """A share over clustered samples (K samples per scene) gets an interval over scenes: all-or-nothing scenes
    carry far less information than their sample count, so the interval is wider than a binomial one over samples,
    and it collapses when every scene has the same share."""
    import numpy as np

    from adlpipe.evaluation.stats import ratio_interval

    den = np.full(40, 8.0)  # 40 scenes, 8 committed samples each
    num = np.where(np.arange(40) < 20, 8.0, 0.0)  # half the scenes all to the demonstrated mode, half none
    lo, hi = ratio_interval(num, den)
    assert lo < 0.5 < hi
    wilson = success_interval(160, 320)
    assert hi - lo > 2 * (wilson[1] - wilson[0])
    assert ratio_interval(np.full(5, 2.0), np.full(5, 4.0)) == (0.5, 0.5)


def test_report_figures_tell_every_series_apart_and_label_the_steps() -> None:
    """X.5: no two models share a colour (BC-CNN and BC-Transformer were the same blue dotted line), and the log
    step axis is labelled with the step counts."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from adlpipe.evaluation.figures import label_steps, model_styles
    from adlpipe.policy.models import MODELS

    styles = model_styles(sorted(MODELS))
    assert len({s["color"] for s in styles.values()}) == len(MODELS)
    assert styles["bc_cnn"]["linestyle"] == ":" and styles["fm_cnn"]["linestyle"] == "-"
    fig, ax = plt.subplots()
    ax.plot([1, 2, 4, 16], [3, 2, 2, 1])
    label_steps(ax, [1, 2, 4, 16])
    fig.canvas.draw()
    assert [t.get_text() for t in ax.get_xticklabels()] == ["1", "2", "4", "16"]
    plt.close(fig)


def test_paired_difference_verdicts() -> None:
    from adlpipe.evaluation.stats import paired_difference

    a, b = [1.0, 2.0, 3.0, 4.0] * 10, [1.2, 2.2, 3.1, 4.3] * 10
    assert paired_difference(a, b).verdict() == "supported" and paired_difference(b, a).verdict() == "contradicted"
    d = paired_difference([1.0, 2.0] * 10, [1.1, 1.93] * 10)  # -0.015 on average, -0.1 or +0.07 per episode
    assert d.verdict().startswith("not resolved at n = 20 (about ") and d.low < 0 < d.high
    assert paired_difference([2.0] * 5, [2.0] * 5).verdict() == "not resolved at n = 5"
    assert paired_difference([1.0], [1.0], scale=1.1).mean == pytest.approx(-0.1)  # within 10 % of the second


def _details(px: dict[str, list[float]], success: dict[str, list[bool]], converged: bool) -> tuple[dict, dict]:
    """Synthetic evaluate / replay details in the stages' own format: one default row per model."""
    keys = {"fm_cnn": ("euler", 1), "dp_cnn": ("ddpm", 16), "bc_cnn": ("direct", 1)}
    models, per_episode, rates = {}, {}, {}
    for m, v in px.items():
        method, steps = keys[m]
        row = {"method": method, "steps": steps, "default": True, "px": sum(v) / len(v), "cm": 2 * sum(v) / len(v),
               "px_per_episode": v}
        models[m] = {"best": {f"{method}/{steps}": row}}
        label = m if method == "direct" else f"{m}/{method}-{steps}"
        per_episode[label] = {f"e{i}": ok for i, ok in enumerate(success[m])}
        rates[label] = {"overall": sum(success[m]) / len(success[m]), "n": len(success[m])}
    ev = {"n_test": len(next(iter(px.values()))), "models": models,
          "training": {m: {"converged": converged} for m in px}}
    return ev, {"success": rates, "per_episode": per_episode}


def test_seeds_summary_spread_and_claims_over_seeds() -> None:
    """Three seeds where FM is clearly ahead of DP on every episode (supported in every seed and over seeds) and
    BC is FM plus zero-mean noise (not resolved): the verdicts and the spread come out as constructed."""
    import numpy as np

    from adlpipe.seeds import summarise

    rng = np.random.default_rng(0)
    evals, replays = [], []
    for seed in range(3):
        base = rng.uniform(2, 4, 40)
        fm = base + 0.1 * seed
        dp = base + 1.0
        bc = fm + rng.normal(0, 0.3, 40) * np.where(np.arange(40) % 2, 1, -1)
        ev, rp = _details({"fm_cnn": list(fm), "dp_cnn": list(dp), "bc_cnn": list(bc)},
                          {"fm_cnn": [i < 10 + seed for i in range(40)], "dp_cnn": [i < 8 for i in range(40)],
                           "bc_cnn": [i < 9 for i in range(40)]}, converged=seed != 1)
        evals.append(ev)
        replays.append(rp)
    s = summarise(evals, replays)
    fm = s["models"]["fm_cnn"]
    assert fm["px"] == pytest.approx([e["models"]["fm_cnn"]["best"]["euler/1"]["px"] for e in evals])
    assert fm["px_sd"] == pytest.approx(np.std(fm["px"], ddof=1))
    assert fm["success"] == pytest.approx([0.25, 0.275, 0.3]) and fm["success_mean"] == pytest.approx(0.275)
    assert fm["converged"] == [True, False, True]
    claims = {c["claim"]: c for c in s["claims"]}
    # no FM-16 row in these details: that claim is left out, not guessed
    assert "FM-16 more accurate than DP-16 (clean-trajectory pair)" not in claims
    c = claims["FM-1 within 10 % of DP-16 (clean-trajectory pair)"]
    assert c["per_seed"] == ["supported"] * 3 and c["over_seeds"] == "supported"
    b = claims["FM-1 more accurate than BC (same U-Net)"]
    assert b["over_seeds"].startswith("not resolved at n = 40")


def test_seeds_refuse_different_test_splits() -> None:
    from adlpipe.plumbing.errors import AdlError
    from adlpipe.seeds import summarise

    a = _details({"fm_cnn": [1.0, 2.0]}, {"fm_cnn": [True, False]}, True)
    b = _details({"fm_cnn": [1.0, 2.0, 3.0]}, {"fm_cnn": [True, False, True]}, True)
    with pytest.raises(AdlError, match="different test splits"):
        summarise([a[0], b[0]], [a[1], b[1]])


def test_where_closed_loop_rollouts_fail_carries_intervals() -> None:
    """The failure-location table's medians (end error, path ratio, still time) print their bootstrap intervals,
    over the failed rollouts only."""
    from adlpipe.evaluation.replay import failure_table

    diags = {f"e{i}": {"failed": ["placed"] if i < 6 else [], "end_error_cm": 10.0 + i, "path_ratio": 0.5,
                       "still_s": 0.1 * i, "demo_still_s": 0.2} for i in range(8)}
    per = {"p/Ta-8": {f"e{i}": i >= 6 for i in range(8)}}
    row = next(x for x in failure_table({"p/Ta-8": diags}, per).splitlines() if x.startswith("| p/Ta-8"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "6 of 8" and cells[6] == "6"  # six failed, each missed the placement
    assert cells[7].startswith("12.5 [") and cells[8] == "0.50 [0.50, 0.50]" and cells[9].endswith("(0.2 [0.2, 0.2])")


def test_mcnemar_verdict_and_the_scenes_that_would_resolve_it() -> None:
    from adlpipe.evaluation.stats import paired_success, scenes_to_resolve

    better = paired_success([1] * 12 + [0] * 2 + [1] * 10 + [0] * 16, [0] * 12 + [1] * 2 + [1] * 10 + [0] * 16)
    assert (better.only_first, better.only_second, better.n) == (12, 2, 40) and better.p_value < 0.05
    assert better.verdict() == "better"
    open_ = paired_success([1] * 4 + [0] * 36, [0] * 3 + [1] + [0] * 36)
    assert open_.verdict().startswith("not resolved at n = 40 (about ")
    need = scenes_to_resolve(4, 1, 40)
    # at the measured share (5 of 40 discordant, 4 : 1) that many scenes give p < 0.05, 10 % fewer do not
    from scipy.stats import binomtest

    k = round(5 / 40 * need)
    assert binomtest(round(0.8 * k), k).pvalue < 0.05
    k0 = round(5 / 40 * int(need * 0.9))
    assert binomtest(round(0.8 * k0), k0).pvalue >= 0.05
    assert scenes_to_resolve(3, 3, 40) is None and paired_success([1, 0], [1, 0]).verdict().endswith(
        "(no difference measured)")
