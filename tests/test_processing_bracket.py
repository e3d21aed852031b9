"""Exposure brackets merged per band: counts over time where a band did not clip."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from sim_frame import one_frame

from m2s2hil.errors import UsageError
from m2s2hil.processing.bracket import merge_bracket
from m2s2hil.processing.errors import BracketError


def test_unclipped_values_pool_their_counts_and_a_clipped_band_falls_back():
    rate = np.array([[[10.0, 400.0]]])  # (1 band, 1, 2): a shadow and a lit face, DN per unit scale
    short = rate * 1.0 + np.array([[[1.0, -3.0]]])  # exposures 1 and 16, a little noise
    long = rate * 16.0 + np.array([[[4.0, 0.0]]])
    ok = np.zeros((1, 1, 2), bool)
    clipped_long = np.array([[[False, True]]])  # the lit face clips in the long frame
    m = merge_bracket([short, long], [1.0, 16.0], [ok, clipped_long])
    assert m.cube[0, 0, 0] == pytest.approx((11.0 + 164.0) / 17.0)  # total counts / total time
    assert m.cube[0, 0, 1] == pytest.approx(397.0)  # the short frame alone, as it was
    assert m.frames_used.tolist() == [[[2, 1]]]
    assert not m.clipped.any()
    both = merge_bracket([short, long], [1.0, 16.0], [clipped_long, clipped_long])
    assert both.clipped.tolist() == [[[False, True]]]
    assert both.cube[0, 0, 1] == pytest.approx(397.0)  # clipped everywhere: the shortest frame's value
    assert both.cube[0, 0, 0] == pytest.approx((11.0 + 164.0) / 17.0)  # clipped in neither


def test_the_result_is_on_the_first_frames_scale():
    rate = np.full((2, 3, 3), 5.0)
    ok = np.zeros(rate.shape, bool)
    m = merge_bracket([rate * 8.0, rate * 2.0], [8.0, 2.0], [ok, ok])
    assert np.allclose(m.cube, rate * 8.0)
    # the scale is exposure × gain: 10 ms at gain 1 and 10 ms at gain 4 bracket like 10 and 40 ms
    gained = merge_bracket([rate * 0.01, rate * 0.04], [0.01 * 1.0, 0.01 * 4.0], [ok, ok])
    assert np.allclose(gained.cube, rate * 0.01)


@pytest.mark.parametrize(("cubes", "scales", "masks", "problem"), [
    ([np.zeros((1, 2, 2))], [1.0, 2.0], [np.zeros((1, 2, 2), bool)], "as many"),
    ([np.zeros((2, 2))], [1.0], [np.zeros((2, 2), bool)], "bands, H, W"),
    ([np.zeros((1, 2, 2)), np.zeros((1, 2, 3))], [1.0, 2.0], [np.zeros((1, 2, 2), bool)] * 2, "frame 1"),
    ([np.zeros((1, 2, 2))] * 2, [1.0, 0.0], [np.zeros((1, 2, 2), bool)] * 2, "> 0"),
    ([np.zeros((1, 2, 2))] * 2, [1.0, float("nan")], [np.zeros((1, 2, 2), bool)] * 2, "finite"),
])
def test_a_bracket_that_does_not_agree_is_a_typed_error(cubes, scales, masks, problem):
    with pytest.raises(BracketError, match=problem) as err:
        merge_bracket(cubes, scales, masks)
    assert isinstance(err.value, UsageError)


def test_a_bracketed_spotlight_frame_has_quieter_shadows_and_keeps_its_lit_faces():
    """The simulator's own path: the same pose at 16 × the exposure, merged. The backdrop (as dark
    as a shadow) is several times quieter; the lit faces, which clip in the long frame, keep the
    short frame's values, so the brightest band stays where the single frame had it."""
    spot = {"size": 256, "lightings": ["directional"], "spot_angle_deg": 80.0}
    single = one_frame("voyager", "B3", **spot)
    merged = one_frame("voyager", "B3", **spot, bracket=16.0)

    def backdrop_noise(f) -> float:  # median |difference| of neighbours, clear of the object's rim
        back = ndimage.binary_erosion(f.gt == 0, iterations=3)
        return float(np.median(np.abs(np.diff(f.cube, axis=2)[:, back[:, :-1] & back[:, 1:]])))

    assert backdrop_noise(merged) < 0.25 * backdrop_noise(single)  # 16 × the light: ≥ 4 × quieter
    obj = single.gt > 0
    top_single = np.percentile(single.cube[:, obj].max(axis=0), 99)
    top_merged = np.percentile(merged.cube[:, obj].max(axis=0), 99)
    assert top_merged == pytest.approx(top_single, rel=0.05)
    assert merged.band_saturated is not None and merged.saturated is not None
    assert np.array_equal(merged.saturated, merged.band_saturated.any(axis=0))
