"""Issue 23, seventh pass: near-tied component counts settled by the label map's coherence
(``segmenters.ties``). The end-to-end test runs the sweep alone (``tie_break=0``) where it failed."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sim_frame import one_frame

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.scores import score_clusters
from m2s2hil.analysis.segmenters import ties
from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter
from m2s2hil.analysis.segmenters.ties import coherence, component_penalty, near_ties
from m2s2hil.analysis.study.simframes import visible_materials
from m2s2hil.analysis.study.synthetic import synthetic_scene


def test_coherence_counts_pixels_whose_labelled_neighbours_agree():
    halves = np.ones((10, 10), dtype=int)
    halves[:, 5:] = 2
    assert coherence(halves) == pytest.approx(0.8)  # columns 4 and 5 touch the other label
    assert coherence(np.indices((10, 10)).sum(axis=0) % 2 + 1) == 0.0  # a checkerboard
    ringed = np.zeros((10, 10), dtype=int)
    ringed[2:8, 2:8] = 3
    assert coherence(ringed) == 1.0  # the backdrop (0) is nobody's neighbour
    assert coherence(np.zeros((4, 4), dtype=int)) == 1.0


def test_one_components_penalty_and_the_near_ties():
    assert component_penalty(11, "full", 2500) == pytest.approx(78 * math.log(2500))
    assert component_penalty(11, "diag", 2500) == pytest.approx(23 * math.log(2500))
    assert component_penalty(11, "tied", 2500) == pytest.approx(12 * math.log(2500))
    scores = {5: -100.0, 6: -700.0, 7: -200.0, 8: -95.0, 4: -690.0}
    assert near_ties(scores, 6, 600.0) == [7]  # above the chosen count only, within the margin
    assert near_ties(scores, 6, 0.0) == []
    with pytest.raises(AnalysisInputError, match="tie_break"):
        SpectralSegmenter(tie_break=-1)


@pytest.fixture(scope="module")
def voyager_b3_at_10_percent():
    # Voyager B3 at 10 % of full scale: 8 visible materials, 6 of them on parts of 100-500 pixels
    return one_frame("voyager", "B3", size=1024, peak_fraction=0.1)


def test_a_near_tie_goes_to_the_count_whose_map_stays_coherent(voyager_b3_at_10_percent):
    f = voyager_b3_at_10_percent
    true = visible_materials(f.gt)
    sweep = SpectralSegmenter(tie_break=0).analyse(f.cube)
    now = SpectralSegmenter().analyse(f.cube)
    assert sweep.n_materials <= true - 2  # the sweep alone: two small-part materials short
    assert abs(now.n_materials - true) <= 1
    assert score_clusters(f.gt, now.labels)[0].macro_dice > score_clusters(f.gt, sweep.labels)[0].macro_dice
    # the criterion of the count chosen is within one component's penalty of the sweep's best
    best = min(sweep.bic, key=sweep.bic.get)
    assert any(n > best for n in near_ties(sweep.bic, best, 78 * math.log(2500)))
    old = SpectralSegmenter(robust=False)
    assert old.tie_break is None and old._tie_break() == 0  # the issue-15 segmenter: the sweep decides


def test_a_larger_count_that_speckles_the_map_is_refused(monkeypatch):
    """Every count a tie (a huge margin) on one noisy material: the larger counts split the noise,
    which speckles the map, so the count stays; without the coherence guard it does not."""
    cube, _ = synthetic_scene((48, 48), n_materials=1, noise=0.05, seed=3)
    wide = SpectralSegmenter(tie_break=1e9, bic_patience=3, merge_angle_deg=0.0)
    kept = wide.analyse(cube).n_materials
    sweep = SpectralSegmenter(tie_break=0, bic_patience=3, merge_angle_deg=0.0)
    assert kept == sweep.analyse(cube).n_materials
    monkeypatch.setattr("m2s2hil.analysis.segmenters.spectral.COHERENCE_TOL", 1.0)  # no guard
    assert ties.COHERENCE_TOL == 0.01
    assert wide.analyse(cube).n_materials > kept
