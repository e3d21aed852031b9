"""How stable the PCA band choice is: a bootstrap over frames (issue 23).

``bands.select_bands_pca`` picks the k bands with the largest loadings on the leading
components of the pooled pixels (the paper's rule; it reports bands 5, 9 and 10). On
simulated sessions the pick moved with the subset of frames (5, 8, 9 on all frames; 1, 4, 9
on 36 of them), so one pick alone says little. Here the frames are resampled with
replacement ``n_boot`` times (each frame's pixels kept together: frames, not pixels, are the
independent units, since pixels of one frame share its pose and light), the pick is redone
on each resample, and the report gives how often each band and each set of k bands was
chosen, beside the pick on all frames.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from m2s2hil.analysis.errors import AnalysisInputError

DEFAULT_BOOTSTRAPS = 200


@dataclass(frozen=True)
class BandStability:
    """The pick on all frames and its bootstrap frequencies (bands 1-based, as reported)."""

    bands: tuple[int, ...]  # the pick on all frames, sorted
    n_frames: int
    n_boot: int
    band_frequency: dict[int, float]  # band -> share of resamples whose pick contains it
    set_frequency: dict[tuple[int, ...], float]  # sorted pick -> share of resamples, most frequent first

    @property
    def pick_frequency(self) -> float:
        """Share of resamples that picked exactly the all-frames set."""
        return self.set_frequency.get(self.bands, 0.0)

    def summary(self, top: int = 3) -> str:
        """One line for a report."""
        sets = "; ".join(f"{', '.join(map(str, s))}: {f:.0%}"
                         for s, f in list(self.set_frequency.items())[:top])
        ranked = sorted(self.band_frequency.items(), key=lambda kv: -kv[1])
        bands = ", ".join(f"{b}: {f:.0%}" for b, f in ranked if f > 0)
        return (f"bands {', '.join(map(str, self.bands))} on all {self.n_frames} frames, picked exactly "
                f"in {self.pick_frequency:.0%} of {self.n_boot} bootstrap resamples of the frames (most "
                f"frequent sets: {sets}; each band chosen in: {bands})")

    def as_dict(self) -> dict[str, object]:
        return {
            "bands": list(self.bands),
            "n_frames": self.n_frames,
            "n_boot": self.n_boot,
            "pick_frequency": self.pick_frequency,
            "band_frequency": {str(b): f for b, f in self.band_frequency.items()},
            "set_frequency": [{"bands": list(s), "share": f} for s, f in self.set_frequency.items()],
        }


def _pick(frames: Sequence[np.ndarray], k: int, standardize: bool) -> tuple[int, ...]:
    """``select_bands_pca``'s rule (component i → its largest |loading| among bands not yet
    picked) on the pooled pixels, by an eigendecomposition of their covariance (correlation when
    standardised): the same components as scikit-learn's PCA up to sign, at a fraction of its
    overhead, which matters for a few hundred resamples (a test holds the two equal)."""
    x = np.concatenate(frames)  # (n, bands)
    x = x - x.mean(axis=0)
    if standardize:
        sd = x.std(axis=0)
        x = x / np.where(sd > 0, sd, 1.0)  # StandardScaler leaves a constant band at 0 too
    _, vecs = np.linalg.eigh(x.T @ x)
    loadings = vecs[:, ::-1].T  # rows = components, largest variance first
    chosen: list[int] = []
    for i in range(k):
        order = np.argsort(-np.abs(loadings[i]), kind="stable")
        chosen.append(int(next(b for b in order if b not in chosen)))
    return tuple(sorted(b + 1 for b in chosen))


def band_stability(
    samples: Sequence[np.ndarray], *, k: int = 3, n_boot: int = DEFAULT_BOOTSTRAPS, seed: int = 0,
    standardize: bool = True,
) -> BandStability:
    """Bootstrap the PCA band pick over frames; ``samples[i]`` is frame i's pixels, ``(n_i, bands)``."""
    frames = [np.asarray(s, dtype=np.float64) for s in samples]
    frames = [f for f in frames if f.ndim == 2 and f.shape[0] > 0]
    if len(frames) < 2:
        raise AnalysisInputError("samples", f"need pixels from at least 2 frames, got {len(frames)}")
    if len({f.shape[1] for f in frames}) != 1:
        raise AnalysisInputError("samples", "frames have different numbers of bands")
    if n_boot < 1:
        raise AnalysisInputError("n_boot", f"must be ≥ 1, got {n_boot}")
    n_bands = frames[0].shape[1]
    full = _pick(frames, k, standardize)
    rng = np.random.default_rng(seed)
    sets: Counter[tuple[int, ...]] = Counter()
    for _ in range(n_boot):
        idx = rng.integers(0, len(frames), size=len(frames))
        sets[_pick([frames[i] for i in idx], k, standardize)] += 1
    band_count = Counter(b for s, c in sets.items() for b in s for _ in range(c))
    return BandStability(
        bands=full,
        n_frames=len(frames),
        n_boot=n_boot,
        band_frequency={b: band_count[b] / n_boot for b in range(1, n_bands + 1)},
        set_frequency={s: c / n_boot for s, c in sets.most_common()},
    )
