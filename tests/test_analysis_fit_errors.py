"""A mixture that cannot be fitted as asked: refitted with more regularisation, or refused with a
typed error naming the option (never sklearn's ValueError at the operator)."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.segmenters import spectral
from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter


class Collapsing:
    """An estimator that fails as sklearn's mixtures do when a component collapses (a ``diag`` fit
    of a one-material build at 60 % peak did, out of ``analyse``) unless regularised enough."""

    def __init__(self, reg: float, needed: float, tried: list[float]) -> None:
        self.reg, self.needed = reg, needed
        tried.append(reg)

    def fit(self, sample: np.ndarray) -> Collapsing:
        if self.reg < self.needed:
            raise ValueError("Fitting the mixture model failed because some components have "
                             "ill-defined empirical covariance (for instance caused by singleton ...)")
        return self


def test_a_collapsing_fit_is_refitted_with_more_regularisation_then_refused():
    sample = np.zeros((10, 3))
    tried: list[float] = []
    fitted = spectral._fitted(lambda reg: Collapsing(reg, 1e-3, tried), sample, 1e-5, "2 components")
    assert fitted.reg == pytest.approx(1e-3) and tried == pytest.approx([1e-5, 1e-4, 1e-3])
    tried.clear()
    with pytest.raises(AnalysisInputError, match="reg_covar") as err:
        spectral._fitted(lambda reg: Collapsing(reg, 1.0, tried), sample, 1e-5, "2 components")
    assert len(tried) == spectral.REG_COVAR_RETRIES + 1 and "2 components" in str(err.value)

    # any other ValueError is not this one, and is not hidden
    class Broken(Collapsing):
        def fit(self, sample: np.ndarray) -> Collapsing:
            raise ValueError("Expected 2D array")

    with pytest.raises(ValueError, match="2D array"):
        spectral._fitted(lambda reg: Broken(reg, 0.0, []), sample, 1e-5, "1 component")


def test_a_fit_that_cannot_be_regularised_is_a_typed_error():
    # an object of one exact spectrum and no regularisation: every covariance is zero
    cube = np.zeros((4, 48, 48))
    cube[:, 12:36, 12:36] = np.array([10.0, 20.0, 30.0, 40.0])[:, None, None]
    with pytest.raises(AnalysisInputError, match="reg_covar") as err:
        SpectralSegmenter(reg_covar=0.0, robust=False).analyse(cube)
    assert "raise reg_covar" in str(err.value)
