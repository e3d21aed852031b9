"""How much a rate measured on a few frames says: the Wilson score interval of a binomial rate.

The robustness goal reads "K within ±1 on ≥ 90 % of frames" from 18 frames a cell, where one frame
is 5.6 points. The interval says which verdicts the frames can tell apart: 15 of 18 (83 %) has a
95 % interval of 61–94 %, which holds 90 %, and so does 18 of 18's (82–100 %). Wilson's interval,
not the normal approximation ±1.96·√(p(1−p)/n): at 18 of 18 that one is 100 % ± 0, and near the
ends of [0, 1] it undercovers (Brown, Cai & DasGupta 2001, "Interval estimation for a binomial
proportion"). ``scipy.stats.binomtest(...).proportion_ci(method="wilson")`` computes it.
"""

from __future__ import annotations

from scipy import stats

from m2s2hil.analysis.errors import AnalysisInputError


def rate_interval(hits: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval (low, high) of the rate ``hits / n`` at ``confidence``."""
    if isinstance(hits, bool) or isinstance(n, bool) or int(hits) != hits or int(n) != n:
        raise AnalysisInputError("hits", f"counts must be whole numbers, got {hits!r} of {n!r}")
    if not 0 <= hits <= n or n < 1:
        raise AnalysisInputError("hits", f"need 0 ≤ hits ≤ n and n ≥ 1, got {hits} of {n}")
    if not 0 < confidence < 1:
        raise AnalysisInputError("confidence", f"must lie in (0, 1), got {confidence}")
    ci = stats.binomtest(int(hits), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)
