"""Near-tied component counts, settled by where the pixels lie (issue 23, seventh pass).

The count sweep scores each count on the fit sample alone, which knows nothing of where its
pixels are. At low light a material on a few small parts (Voyager B3 at 10 % peak: parts of
100–350 pixels, 9–26 of them in the stride-2 fit sample) adds less likelihood than one more
component costs, and the sweep's criterion for 6, 7 and 8 components lies within 330 of
−183 000, i.e. within one component's penalty (78 parameters × ln n ≈ 610 at full
covariance, 11 features, n ≈ 2 500). A tie of that size is no evidence either way; the image
has some: a real material covers parts, so labelling with one more component keeps the map as
*coherent* (pixels whose four neighbours share their label) as before, where a component
fitted to noise or shading speckles it.

So among the counts above the chosen one whose criterion is within ``tie_break`` component
penalties of it, the largest whose labelling has more materials and a coherence no more than
``COHERENCE_TOL`` below the chosen one's wins.
"""

from __future__ import annotations

import math

import numpy as np

# How much less coherent the map of a larger count may be (fraction of the foreground's pixels)
COHERENCE_TOL = 0.01


def coherence(labels: np.ndarray) -> float:
    """Fraction of the labelled pixels (> 0) whose labelled 4-neighbours all share their label."""
    lab = np.asarray(labels)
    fg = lab > 0
    if not fg.any():
        return 1.0
    keep = fg.copy()
    down = (lab[1:] != lab[:-1]) & fg[1:] & fg[:-1]  # pairs of labelled pixels that differ
    keep[1:] &= ~down
    keep[:-1] &= ~down
    side = (lab[:, 1:] != lab[:, :-1]) & fg[:, 1:] & fg[:, :-1]
    keep[:, 1:] &= ~side
    keep[:, :-1] &= ~side
    return float(keep[fg].mean())


def component_penalty(n_features: int, covariance_type: str, n_samples: int) -> float:
    """What one more component adds to BIC's penalty: its mean, its covariance (none when tied)
    and its weight, each × ln n."""
    d = int(n_features)
    cov = {"full": d * (d + 1) // 2, "diag": d, "spherical": 1, "tied": 0}[covariance_type]
    return (d + cov + 1) * math.log(max(int(n_samples), 2))


def near_ties(scores: dict[int, float], chosen: int, margin: float) -> list[int]:
    """Counts above ``chosen`` whose score is within ``margin`` of its, ascending."""
    return sorted(n for n, v in scores.items() if n > chosen and v - scores[chosen] <= margin)
