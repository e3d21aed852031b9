"""Issue 23, ninth pass: cells that are part object, part gap (``edge_step``) stay out of the fit."""

from __future__ import annotations

import numpy as np
import pytest
from sim_frame import one_frame

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics.scores import score_clusters
from m2s2hil.analysis.segmenters.spectral import SpectralSegmenter, darker_than_a_neighbour
from m2s2hil.analysis.study.simframes import visible_materials


def test_the_dark_side_of_a_step_is_a_blend_and_the_bright_side_is_not():
    energy = np.full((7, 9), 100.0)
    energy[:, 4] = 30.0  # a one-pixel gap through a panel
    energy[:, 3] = 75.0  # a cell partly over the gap: darker than its left neighbour by log(100/75)
    found = darker_than_a_neighbour(energy, 0.2)
    assert found[:, 4].all() and found[:, 3].all()  # both darker than a neighbour by > e^0.2
    assert not found[:, [0, 1, 2, 5, 6, 7, 8]].any()  # the panel beside them is darker than nothing
    assert not darker_than_a_neighbour(energy, 1.3).any()  # log(100/30) = 1.2 is under that step
    bar = np.full((9, 9), 1.0)
    bar[:, 3:6] = [60.0, 100.0, 60.0]  # a boom three pixels wide, its sides partly over the backdrop
    found = darker_than_a_neighbour(bar, 0.2)
    assert not found[:, 4].any() and found[:, 3].all() and found[:, 5].all()  # its ridge stays
    with pytest.raises(AnalysisInputError, match="edge_step"):
        SpectralSegmenter(edge_step=-0.1)
    with pytest.raises(AnalysisInputError, match="blend_filter_step"):
        SpectralSegmenter(blend_filter_step=float("nan"))


def test_a_blend_the_mosaic_garbled_is_told_from_shading():
    """Shading darkens a surface and keeps its spectral shape; a cell over a gap changes shape."""
    shape = np.linspace(1.0, 2.0, 10)
    cube = np.ones((10, 6, 8)) * shape[:, None, None]
    cube[:, :, 4:] *= 0.4  # a face turned from the light: darker by e^0.9, the same shape
    garbled = shape.copy()
    garbled[3], garbled[7] = 0.0, 4.0  # one band over the gap, another over the panel
    cube[:, 2, 2] = 0.4 * garbled  # and darker: part of the cell is gap
    energy = np.linalg.norm(cube, axis=0)
    unit = cube / energy
    found = darker_than_a_neighbour(energy, 0.5, unit, 5.0)
    assert found[2, 2] and found.sum() == 1  # the garbled cell alone
    assert darker_than_a_neighbour(energy, 0.5)[:, 4].all()  # brightness alone takes the shaded edge too
    assert not darker_than_a_neighbour(energy, 0.5, unit, 90.0).any()  # no shape differs by 90°
    with pytest.raises(AnalysisInputError, match="blend_filter_angle"):
        SpectralSegmenter(blend_filter_angle=-1.0)


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_the_gaps_between_solar_panels_no_longer_split_one_material():
    # ISS B1 (pro silver alone) at 180°: the cells beside the one-pixel gaps between the panels' cells
    # were fitted as two more materials, stripes along each gap
    f = one_frame("iss", "B1", size=1024, azimuths=[180.0])
    assert visible_materials(f.gt) == 1
    before = SpectralSegmenter().analyse(f.cube)
    now = SpectralSegmenter(edge_step=0.2).analyse(f.cube)
    assert before.n_materials >= 3 and now.n_materials == 1
    assert score_clusters(f.gt, now.labels)[0].macro_dice > score_clusters(f.gt, before.labels)[0].macro_dice
    assert before.fit.sum() > now.fit.sum() > 0.95 * before.fit.sum()  # a few pixels, the blends
