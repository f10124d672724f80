"""The statistics the tables print: Wilson intervals and McNemar's exact test, against known answers."""

from __future__ import annotations

import pytest

from adlpipe.stats import paired_success, rate_cell, success_interval


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

    from adlpipe.stats import mean_cell, mean_interval

    x = np.random.default_rng(4).normal(2.0, 1.0, 400)
    lo, hi = mean_interval(x)
    half = 1.96 * x.std(ddof=1) / np.sqrt(len(x))  # ~0.098
    assert lo == pytest.approx(x.mean() - half, abs=0.02) and hi == pytest.approx(x.mean() + half, abs=0.02)
    assert mean_interval(x) == (lo, hi)  # seeded: a table re-made from the same episodes prints the same interval
    assert mean_interval([0.5, 0.5, 0.5]) == (0.5, 0.5) and mean_interval([0.7]) == (0.7, 0.7)
    assert mean_cell([0.0, 1.0] * 50) == "0.500 [0.400, 0.600]"


def test_report_figures_tell_every_series_apart_and_label_the_steps() -> None:
    """X.5: no two models share a colour (BC-CNN and BC-Transformer were the same blue dotted line), and the log
    step axis is labelled with the step counts."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from adlpipe.policy.models import MODELS
    from adlpipe.report import label_steps, model_styles

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
    from adlpipe.stats import paired_difference

    a, b = [1.0, 2.0, 3.0, 4.0] * 10, [1.2, 2.2, 3.1, 4.3] * 10
    assert paired_difference(a, b).verdict() == "supported" and paired_difference(b, a).verdict() == "contradicted"
    d = paired_difference([1.0, 2.0] * 10, [1.1, 1.93] * 10)  # -0.015 on average, -0.1 or +0.07 per episode
    assert d.verdict().startswith("not resolved at n = 20 (about ") and d.low < 0 < d.high
    assert paired_difference([2.0] * 5, [2.0] * 5).verdict() == "not resolved at n = 5"
    assert paired_difference([1.0], [1.0], scale=1.1).mean == pytest.approx(-0.1)  # within 10 % of the second
