"""The continuous estimate against a real simulated continuous run on the virtual clock."""

from __future__ import annotations

import pytest
from engine_helpers import session, small_rig_config, small_sweep

from m2s2hil.plan import estimate_continuous

TOLERANCE = 0.03  # the estimate leaves out serial round trips, the stream's start and 50 ms status polls


@pytest.mark.slow  # ~2 s: a real continuous session (2 conditions x 2 tilts, 4 passes)
def test_the_continuous_estimate_matches_a_simulated_run_and_stays_above_the_floor(tmp_path) -> None:
    cfg = small_rig_config()
    sweep = small_sweep(mode="continuous", lighting=["weak", "directional"], tilts=["E0", "E1"],
                        azimuth_step_deg=30)
    est = estimate_continuous(sweep, cfg, radius_px=400.0)
    floor = sweep.physical_floor(cfg).total_s
    with session(tmp_path, sweep) as s:
        st = s.engine.run()
        assert st.done == st.total
        run_s = st.elapsed_s
    assert est.total_s >= floor
    assert est.lower_bound_s <= est.total_s
    assert est.total_s == pytest.approx(run_s, rel=TOLERANCE), (est.total_s, run_s, est.breakdown)
