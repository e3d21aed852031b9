"""Paired t-test with an assumed correlation: hand values, scipy equivalence, ρ sweep."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy import stats

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.significance import (
    SENSITIVITY_RHOS,
    format_sensitivity,
    paired_t_test,
    rho_sensitivity,
)


def test_hand_computed_example_at_rho_0_9() -> None:
    a = [2.0, 4.0, 6.0, 8.0]  # mean 5, s² = 20/3
    b = [1.0, 3.0, 5.0, 7.0]  # mean 4, s² = 20/3
    r = paired_t_test(a, b, rho=0.9)
    # SD_diff² = 20/3 + 20/3 − 2·0.9·20/3 = 4/3; t = 1 / (sqrt(4/3)/2) = sqrt(3)
    assert r.sd_diff == pytest.approx(math.sqrt(4 / 3))
    assert r.t == pytest.approx(math.sqrt(3))
    assert r.df == 3
    # Student t with 3 df: F(t) = 1/2 + (x/(1+x²) + atan x)/π with x = t/√3 = 1
    cdf = 0.5 + (1 / 2 + math.pi / 4) / math.pi
    assert r.p == pytest.approx(2 * (1 - cdf))  # 0.18169...
    assert not r.significant(0.05) and r.stars == ""
    assert r.mean_diff == pytest.approx(1.0)


def test_observed_correlation_equals_ttest_rel() -> None:
    rng = np.random.default_rng(7)
    base = rng.uniform(0.5, 0.9, 30)
    a = base + rng.normal(0.02, 0.02, 30)
    b = base + rng.normal(0.0, 0.03, 30)
    ours = paired_t_test(a, b, rho="observed")
    ref = stats.ttest_rel(a, b)
    assert ours.rho == pytest.approx(np.corrcoef(a, b)[0, 1])
    assert ours.t == pytest.approx(float(ref.statistic), rel=1e-10)
    assert ours.p == pytest.approx(float(ref.pvalue), rel=1e-8)
    assert ours.sd_diff == pytest.approx(np.std(a - b, ddof=1))


def test_rho_sweep_is_monotone_and_ends_with_observed() -> None:
    rng = np.random.default_rng(1)
    a = rng.uniform(0.6, 0.8, 12)
    b = a - 0.01 + rng.normal(0, 0.005, 12)
    rows = rho_sensitivity(a, b)
    assert [r.rho for r in rows[:-1]] == list(SENSITIVITY_RHOS)
    assert rows[-1].rho == pytest.approx(rows[-1].rho_observed)
    p = [r.p for r in rows[:-1]]
    assert all(x > y for x, y in itertools.pairwise(p))  # higher ρ -> smaller SD_diff -> smaller p
    table = format_sensitivity(rows)
    assert table.count("\n") == len(rows) + 1
    assert "(observed)" in table.splitlines()[-1]


def test_significance_levels_and_stars() -> None:
    a = [0.80, 0.82, 0.85, 0.79, 0.88, 0.84, 0.81, 0.86]
    b = [x - 0.05 for x in a]
    r = paired_t_test(a, b, rho=0.9)
    assert r.p < 0.01 and r.stars == "**" and r.significant(0.05)
    assert r.as_dict()["significant_0.01"] is True


def test_degenerate_cases_follow_scipy() -> None:
    same = paired_t_test([1.0, 2.0, 3.0], [1.0, 2.0, 3.0], rho="observed")
    assert math.isnan(same.t) and math.isnan(same.p)
    shift = paired_t_test([1.0, 2.0, 3.0], [0.0, 1.0, 2.0], rho=1.0)
    assert shift.t == math.inf and shift.p == 0.0


@pytest.mark.parametrize(
    ("a", "b", "rho", "argument"),
    [
        ([1.0, 2.0], [1.0], 0.9, "b"),
        ([1.0], [2.0], 0.9, "a"),
        ([1.0, 2.0], [1.0, 3.0], 1.5, "rho"),
        ([1.0, 2.0], [1.0, 3.0], "assumed", "rho"),
        ([1.0, float("nan")], [1.0, 3.0], 0.9, "a"),
    ],
)
def test_bad_input(a: list[float], b: list[float], rho: float | str, argument: str) -> None:
    with pytest.raises(AnalysisInputError) as err:
        paired_t_test(a, b, rho)  # type: ignore[arg-type]
    assert err.value.argument == argument


def test_assumed_and_observed_side_by_side() -> None:
    from m2s2hil.analysis.metrics.significance import assumed_and_observed

    a = [0.90, 0.70, 0.80, 0.60, 0.85, 0.65, 0.75, 0.72]
    b = [0.62, 0.78, 0.58, 0.76, 0.64, 0.72, 0.60, 0.70]  # anti-correlated with a
    both = assumed_and_observed(a, b, rho=0.9)
    assert both.assumed.rho == 0.9 and both.assumed.stars == "**"
    assert both.observed.p == pytest.approx(stats.ttest_rel(a, b).pvalue) and both.observed.stars == ""
    assert both.rho_observed == pytest.approx(stats.pearsonr(a, b).statistic)
    assert not both.agree and "at observed ρ = -0.75" in both.describe()
    # A clear difference carries the same marks, in the same direction, at either ρ.
    same = assumed_and_observed([0.80, 0.82, 0.84, 0.86, 0.88], [0.70, 0.73, 0.73, 0.765, 0.78])
    assert same.assumed.stars == same.observed.stars == "**" and same.agree
    const = assumed_and_observed([1.0, 1.0, 1.0], [0.5, 0.6, 0.7])
    assert math.isnan(const.rho_observed) and "undefined" in const.describe()
