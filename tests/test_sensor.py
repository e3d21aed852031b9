"""The simulated sensor has the statistics it claims."""

from __future__ import annotations

import numpy as np
import pytest
from m2s2hil.simulators.sensor import Sensor, SensorParams, sensor_params_from
from m2s2hil.simulators.shading import Lights, shade

BANDS = (431, 479, 515, 567, 611, 666, 719, 775, 820, 877)
FWHM = (65, 47, 42, 37, 36, 34, 33, 31, 31, 31)
LAYOUT4 = ((0, 1, 2, 3), (4, 5, 6, 7), (8, 9, 0, 1), (2, 3, 4, 5))
N = 256


def make(params: SensorParams | None = None, layout=LAYOUT4, size: int = N, seed: int = 0, **kw) -> Sensor:
    p = params or SensorParams(hot_pixel_fraction=0.0, **kw)
    return Sensor(size, size, layout, BANDS[: max(map(max, layout)) + 1], FWHM[: max(map(max, layout)) + 1],
                  1023, p, seed=seed)


def temporal_var(sensor: Sensor, rate, t: float, gain: float = 1.0, temp: float = 25.0) -> float:
    a = sensor.expose(rate, t, gain, temp).astype(np.float64)
    b = sensor.expose(rate, t, gain, temp).astype(np.float64)
    return float(np.var(a - b) / 2.0)


def test_dark_level_grows_with_exposure_as_configured():
    s = make(dark_current_e_per_s=2000.0, dark_nonuniformity=0.0)
    conv = 1.0 / s.params.e_per_dn
    for t in (0.01, 0.5, 2.0):
        frame = s.expose(None, t, 1.0, 25.0).astype(np.float64)
        expected = s.params.black_level_dn + 2000.0 * t * conv
        assert frame.mean() == pytest.approx(expected, abs=0.05 + 0.002 * expected)
        assert np.allclose(s.expected_dark_dn(t, 1.0, 25.0).mean(), expected, rtol=1e-3)


def test_dark_noise_grows_with_exposure():
    s = make(dark_current_e_per_s=2000.0, dark_nonuniformity=0.0)
    conv = 1.0 / s.params.e_per_dn
    read = s.params.read_noise_e
    for t in (0.001, 1.0, 4.0):  # up to 8000 e: below the full well
        dark_e = 2000.0 * t
        expected = (read**2 + dark_e) * conv**2 + 1.0 / 12.0  # + quantisation
        assert temporal_var(s, None, t) == pytest.approx(expected, rel=0.06)


def test_dark_current_doubles_every_doubling_interval():
    s = make(dark_current_e_per_s=1000.0, dark_doubling_c=6.5, dark_nonuniformity=0.0)
    base = s.params.black_level_dn
    d25 = s.expose(None, 2.0, 1.0, 25.0).mean() - base
    d31 = s.expose(None, 2.0, 1.0, 31.5).mean() - base
    d38 = s.expose(None, 2.0, 1.0, 38.0).mean() - base
    assert d31 / d25 == pytest.approx(2.0, rel=0.03)
    assert d38 / d25 == pytest.approx(4.0, rel=0.03)


def test_fixed_pattern_offset_is_fixed_and_seeded():
    s1, s2, s3 = make(seed=7), make(seed=7), make(seed=8)
    assert np.array_equal(s1.offset_dn, s2.offset_dn)
    assert not np.array_equal(s1.offset_dn, s3.offset_dn)
    # Averaging many dark frames converges on the fixed pattern, not on a flat level.
    mean = np.mean([s1.expose(None, 1e-3).astype(np.float32) for _ in range(32)], axis=0)
    r = np.corrcoef(mean.ravel(), s1.offset_dn.ravel())[0, 1]
    assert r > 0.5
    assert s1.offset_dn.std() == pytest.approx(s1.params.dsnu_dn, rel=0.05)


def test_hot_pixels_are_a_fixed_set_growing_with_exposure():
    p = SensorParams(hot_pixel_fraction=1e-3, hot_pixel_e_per_s=2e4, hot_pixel_spread=0.0)
    s, again = make(p, seed=3), make(p, seed=3)
    assert len(s.hot_pixels) == round(1e-3 * N * N)
    assert np.array_equal(s.hot_pixels, again.hot_pixels)
    short = s.expose(None, 0.001).ravel().astype(np.float64)
    long = s.expose(None, 0.2).ravel().astype(np.float64)
    expected_long = s.params.black_level_dn + 2e4 * 0.2 / s.params.e_per_dn
    assert np.median(long[s.hot_pixels]) == pytest.approx(expected_long, rel=0.05)
    assert np.median(short[s.hot_pixels]) < s.params.black_level_dn + 5
    # Seen as outliers: many more stand out in the long exposure.
    assert (long > 100).sum() >= len(s.hot_pixels) * 0.99 > (short > 100).sum()


def test_shot_noise_variance_is_proportional_to_signal():
    s = make()
    gain = 2.0
    conv = gain / s.params.e_per_dn
    levels = np.array([500.0, 2000.0, 4000.0, 6000.0])  # mean electrons
    var_e = []
    for e in levels:
        rate = np.full((N, N), e / 0.01, dtype=np.float32)
        var_e.append(temporal_var(s, rate, 0.01, gain) / conv**2)
    slope, intercept = np.polyfit(levels, var_e, 1)
    assert slope == pytest.approx(1.0, rel=0.05)  # Poisson: variance = mean (in electrons)
    assert intercept == pytest.approx(s.params.read_noise_e**2, abs=60.0)


def test_gain_scales_the_signal():
    s = make(dsnu_dn=0.0)
    rate = np.full((N, N), 3000.0 / 0.01, dtype=np.float32)
    m1 = s.expose(rate, 0.01, 1.0).mean() - s.params.black_level_dn
    m2 = s.expose(rate, 0.01, 2.0).mean() - s.params.black_level_dn
    assert m1 == pytest.approx(3000.0 / s.params.e_per_dn, rel=0.01)
    assert m2 / m1 == pytest.approx(2.0, rel=0.01)


def test_saturation_at_full_scale():
    s = make()
    frame = s.expose(np.full((N, N), 1e9, dtype=np.float32), 0.01)
    assert frame.dtype == np.uint16
    assert np.all(frame == 1023)
    # Just below the full well: unsaturated on average, never above full scale.
    e = 0.9 * s.params.full_well_e
    frame = s.expose(np.full((N, N), e / 0.01, dtype=np.float32), 0.01)
    assert frame.max() <= 1023
    assert frame.mean() == pytest.approx(e / s.params.e_per_dn + s.params.black_level_dn, rel=0.01)
    # High gain reaches the ADC's full scale before the full well.
    frame = s.expose(np.full((N, N), e / 0.01, dtype=np.float32), 0.01, gain=4.0)
    assert np.all(frame == 1023)


def test_averaging_frames_lowers_noise_by_sqrt_n():
    """The noise pool is read at a random offset per frame: frames are independent."""
    s = make()
    frames = np.stack([s.expose(None, 1e-3).astype(np.float64) for _ in range(16)])
    single = np.std(frames[0] - s.offset_dn)
    averaged = np.std(frames.mean(axis=0) - s.offset_dn)
    # Quantisation noise does not average like Gaussian noise; allow for it.
    assert averaged == pytest.approx(single / 4.0, rel=0.2)


@pytest.mark.parametrize(
    "layout",
    [
        LAYOUT4,
        ((0, 1, 2), (3, 4, 5), (6, 7, 8)),
        ((0, 1, 2, 3, 4), (5, 6, 7, 8, 9), (0, 2, 4, 6, 8), (1, 3, 5, 7, 9), (9, 8, 7, 6, 5)),
    ],
    ids=["4x4", "3x3", "5x5"],
)
def test_mosaic_positions_see_their_band(layout):
    """A flat field with a different reflectance in every band, through shading and the sensor."""
    n = len(layout)
    size = 60 * n
    nb = max(map(max, layout)) + 1
    sensor = make(layout=layout, size=size)
    label = np.ones((size, size), dtype=np.uint8)
    depth = np.zeros((size, size), dtype=np.float32)
    nrm = np.zeros((3, size, size), dtype=np.float32)
    nrm[2] = 1.0
    lights = Lights(dirs=np.array([[0.0, 0.0, 1.0]]), irradiance=np.array([1.0]), gloss=np.array([1.0]),
                    shadowed=np.array([False]), ambient=0.0)
    rho = np.zeros((2, nb), dtype=np.float32)
    rho[1] = 0.1 + 0.08 * np.arange(nb)  # distinct and increasing with band index
    spec = np.zeros_like(rho)
    _, _, rate = shade(label, depth, nrm, (size / 2, size / 2), 1.0, lights, None, rho, spec,
                       np.ones(2, np.float32), np.full(nb, 1e6, np.float32), np.asarray(layout), 0.0)
    frame = sensor.expose(rate, 0.01).astype(np.float64) - sensor.offset_dn
    conv = 0.01 * 1e6 / sensor.params.e_per_dn
    for i in range(n):
        for j in range(n):
            band = layout[i][j]
            seen = frame[i::n, j::n].mean()
            assert seen == pytest.approx(rho[1, band] * conv, rel=0.01)
    assert np.array_equal(sensor.band_map()[:n, :n], np.asarray(layout))


def test_bad_inputs_are_rejected():
    s = make()
    with pytest.raises(ValueError, match="exposure"):
        s.expose(None, 0.0)
    with pytest.raises(ValueError, match="gain"):
        s.expose(None, 0.01, gain=-1.0)
    with pytest.raises(ValueError, match="signal is"):
        s.expose(np.zeros((4, 4), np.float32), 0.01)
    with pytest.raises(ValueError, match="multiple"):
        Sensor(250, 250, LAYOUT4, BANDS, FWHM, 1023)
    with pytest.raises(ValueError, match="read_noise_e"):
        SensorParams(read_noise_e=-1.0)
    with pytest.raises(KeyError, match="read_nois"):
        sensor_params_from({"read_nois": 3})
    assert sensor_params_from({"read_noise_e": 3}).read_noise_e == 3
