"""The Wilson interval of a rate on few frames (analysis/metrics/rates.py)."""

from __future__ import annotations

import math

import pytest
from scipy import stats

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.rates import rate_interval


def wilson(hits: int, n: int, z: float) -> tuple[float, float]:
    """The score interval's closed form (Wilson 1927), written out independently of scipy."""
    p = hits / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


@pytest.mark.parametrize(("hits", "n"), [(15, 18), (16, 18), (18, 18), (0, 18), (30, 36), (1, 2)])
def test_the_interval_is_wilsons(hits: int, n: int) -> None:
    low, high = rate_interval(hits, n)
    want = wilson(hits, n, stats.norm.ppf(0.975))
    assert (low, high) == pytest.approx(want, abs=1e-9)
    assert 0.0 <= low <= hits / n <= high <= 1.0


def test_the_frames_of_one_cell_cannot_tell_83_from_90_percent() -> None:
    # the robustness goal's reading: 15 of 18 and 18 of 18 both hold 90 %; 12 of 18 does not
    assert rate_interval(15, 18)[0] < 0.9 < rate_interval(15, 18)[1]
    assert rate_interval(18, 18)[0] < 0.9
    assert rate_interval(12, 18)[1] < 0.9


@pytest.mark.parametrize("p", [0.5, 0.83, 0.9, 0.95, 0.97])
def test_the_interval_covers_the_true_rate_about_as_often_as_it_says(p: float) -> None:
    # exact coverage over every outcome of 18 frames. Wilson's oscillates around 95 % (0.90 at
    # p = 0.97 is its low point here); the normal approximation's falls to 60 % at p = 0.95 and
    # 42 % at 0.97, where 18 of 18 gives it a zero-width interval
    n = 18

    def normal(k: int) -> tuple[float, float]:
        q = k / n
        half = 1.96 * math.sqrt(q * (1 - q) / n)
        return q - half, q + half

    def coverage(interval) -> float:  # type: ignore[no-untyped-def]
        return float(sum(stats.binom.pmf(k, n, p) for k in range(n + 1)
                         if interval(k)[0] <= p <= interval(k)[1]))

    ours = coverage(lambda k: rate_interval(k, n))
    assert ours >= 0.89, ours
    assert ours > coverage(normal), (ours, coverage(normal))


@pytest.mark.parametrize(("hits", "n", "confidence", "name"), [
    (19, 18, 0.95, "hits"), (-1, 18, 0.95, "hits"), (0, 0, 0.95, "hits"), (1.5, 18, 0.95, "hits"),
    (True, 18, 0.95, "hits"), (3, 18, 1.0, "confidence"), (3, 18, 0.0, "confidence")])
def test_bad_counts_say_what_is_wrong(hits: object, n: int, confidence: float, name: str) -> None:
    with pytest.raises(AnalysisInputError) as err:
        rate_interval(hits, n, confidence)  # type: ignore[arg-type]
    assert err.value.argument == name
