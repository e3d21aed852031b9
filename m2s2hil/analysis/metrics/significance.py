"""Paired t-test over images with an assumed within-image correlation (paper 2.4.2).

The paper compares two methods (e.g. RGB vs multispectral) on the same images "via
paired t-tests at α = 0.05 and 0.01 with an assumed within-image correlation ρ = 0.9".
We read that as the Cochrane Handbook (16.4.6) imputation of the SD of the paired
differences from the two per-method SDs and a correlation:

    s_a, s_b  = sample SDs (ddof = 1) of the per-image scores a_i, b_i (i = 1..n)
    SD_diff   = sqrt(s_a² + s_b² − 2·ρ·s_a·s_b)
    t         = mean(a − b) / (SD_diff / sqrt(n)),   df = n − 1
    p         = two-sided, 2·(1 − F_t(|t|; df))       (scipy.stats.t.sf)

With ρ set to the observed Pearson correlation of a and b, SD_diff is exactly the SD of
the differences and the test equals ``scipy.stats.ttest_rel`` (``rho="observed"``,
computed as SD(a − b) directly to avoid cancellation).
t > 0 means method a scored higher. Because ρ is an assumption, report
``rho_sensitivity`` (ρ = 0, 0.5, 0.8, 0.9, 0.95, 0.99 by default) next to the verdict, and
``assumed_and_observed`` (the test at the assumed ρ beside the test at the observed one, with
whether their marks agree): issue 23 found observed ρ from −0.78 to 1.00 across Table 2's rows
on simulated sessions, and verdicts such as p = 3·10⁻⁵ at ρ = 0.9 but 0.07 at the observed ρ.

Degenerate cases follow scipy: SD_diff = 0 gives t = ±inf, p = 0 when the mean
difference is non-zero, and t = p = NaN when it is zero.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import stats

from m2s2hil.analysis.errors import AnalysisInputError

ALPHAS: tuple[float, float] = (0.05, 0.01)
DEFAULT_RHO = 0.9
SENSITIVITY_RHOS: tuple[float, ...] = (0.0, 0.5, 0.8, 0.9, 0.95, 0.99)


@dataclass(frozen=True)
class PairedTest:
    """One paired comparison of per-image scores ``a`` (method A) and ``b`` (method B)."""

    n: int
    rho: float  # correlation used for SD_diff
    rho_observed: float  # Pearson r of a and b (NaN if either is constant)
    mean_a: float
    mean_b: float
    mean_diff: float  # mean(a − b)
    sd_a: float
    sd_b: float
    sd_diff: float
    t: float
    df: int
    p: float  # two-sided

    def significant(self, alpha: float = 0.05) -> bool:
        """True if the two-sided p-value is below ``alpha``."""
        return bool(self.p < alpha)

    @property
    def stars(self) -> str:
        """``"**"`` at α = 0.01, ``"*"`` at α = 0.05, else ``""`` (the paper: italic / bold)."""
        if self.significant(ALPHAS[1]):
            return "**"
        return "*" if self.significant(ALPHAS[0]) else ""

    def as_dict(self) -> dict[str, float | int | bool]:
        out: dict[str, float | int | bool] = {k: getattr(self, k) for k in self.__dataclass_fields__}
        for alpha in ALPHAS:
            out[f"significant_{alpha:g}"] = self.significant(alpha)
        return out


def _scores(values: object, argument: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.ndim != 1:
        raise AnalysisInputError(argument, f"expected 1-D per-image scores, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise AnalysisInputError(argument, "contains NaN or infinite scores (drop or fill them first)")
    return arr


def observed_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson r of two score vectors; NaN when either is constant."""
    if a.std() == 0 or b.std() == 0:
        return float("nan")
    return float(stats.pearsonr(a, b).statistic)


def paired_t_test(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray,
                  rho: float | Literal["observed"] = DEFAULT_RHO) -> PairedTest:
    """Paired t-test of ``a`` against ``b`` (same images, same order) with correlation ``rho``."""
    av, bv = _scores(a, "a"), _scores(b, "b")
    if av.shape != bv.shape:
        raise AnalysisInputError("b", f"has {bv.size} scores but a has {av.size}; pairs must align")
    n = int(av.size)
    if n < 2:
        raise AnalysisInputError("a", f"a paired t-test needs at least 2 images, got {n}")
    r_obs = observed_correlation(av, bv)
    if isinstance(rho, str):
        if rho != "observed":
            raise AnalysisInputError("rho", f"expected a number in [-1, 1] or 'observed', got {rho!r}")
        r = 0.0 if math.isnan(r_obs) else r_obs  # a constant series has no covariance term
    else:
        r = float(rho)
        if not -1.0 <= r <= 1.0:
            raise AnalysisInputError("rho", f"correlation must lie in [-1, 1], got {rho!r}")
    sd_a = float(np.std(av, ddof=1))
    sd_b = float(np.std(bv, ddof=1))
    if isinstance(rho, str):
        # Algebraically the same as the formula with r = r_obs, without its cancellation error.
        sd_diff = float(np.std(av - bv, ddof=1))
    else:
        var = sd_a**2 + sd_b**2 - 2.0 * r * sd_a * sd_b
        sd_diff = math.sqrt(max(var, 0.0))  # rounding can leave a tiny negative at ρ = 1
    mean_diff = float(np.mean(av - bv))
    df = n - 1
    if sd_diff > 0:
        t = mean_diff / (sd_diff / math.sqrt(n))
        p = float(2.0 * stats.t.sf(abs(t), df))
    elif mean_diff != 0:
        t, p = math.copysign(math.inf, mean_diff), 0.0
    else:
        t, p = float("nan"), float("nan")
    return PairedTest(n, r, r_obs, float(av.mean()), float(bv.mean()), mean_diff, sd_a, sd_b, sd_diff,
                      float(t), df, p)


def rho_sensitivity(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray,
                    rhos: Sequence[float] = SENSITIVITY_RHOS) -> list[PairedTest]:
    """``paired_t_test`` at each assumed ρ, plus the observed correlation as the last row."""
    rows = [paired_t_test(a, b, r) for r in rhos]
    rows.append(paired_t_test(a, b, "observed"))
    return rows


def format_sensitivity(rows: Sequence[PairedTest]) -> str:
    """A Markdown table of a ρ sweep: ρ, SD_diff, t, df, p and the verdict at α = 0.05 / 0.01."""
    lines = ["| ρ | SD_diff | t | df | p | α=0.05 | α=0.01 |", "|---|---|---|---|---|---|---|"]
    yes = {True: "yes", False: "no"}
    for row in rows:
        rho = f"{row.rho:.4g}" + (" (observed)" if row.rho == row.rho_observed else "")
        lines.append(
            f"| {rho} | {row.sd_diff:.4g} | {row.t:.4g} | {row.df} | {row.p:.3g} "
            f"| {yes[row.significant(0.05)]} | {yes[row.significant(0.01)]} |"
        )
    return "\n".join(lines)


@dataclass(frozen=True)
class AssumedVsObserved:
    """The same comparison tested at the assumed ρ and at the observed correlation."""

    assumed: PairedTest
    observed: PairedTest  # ``paired_t_test(a, b, "observed")``: equals scipy.stats.ttest_rel

    @property
    def rho_observed(self) -> float:
        return self.observed.rho_observed

    @property
    def agree(self) -> bool:
        """True when both give the same marks (and, when significant, the same direction)."""
        if self.assumed.stars != self.observed.stars:
            return False
        return not self.assumed.stars or math.copysign(1, self.assumed.mean_diff) == math.copysign(
            1, self.observed.mean_diff)

    def describe(self) -> str:
        """One line: p at the assumed ρ and at the observed one (for a table note)."""
        r = self.rho_observed
        r_text = "undefined (a constant series; ρ = 0 used)" if math.isnan(r) else f"{r:.2f}"
        return (f"p = {self.assumed.p:.2g} at assumed ρ = {self.assumed.rho:g}, "
                f"p = {self.observed.p:.2g} at observed ρ = {r_text}")


def assumed_and_observed(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray,
                         rho: float = DEFAULT_RHO) -> AssumedVsObserved:
    """``paired_t_test`` at the assumed ``rho`` and at the observed correlation of ``a`` and ``b``."""
    return AssumedVsObserved(paired_t_test(a, b, rho), paired_t_test(a, b, "observed"))
