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
