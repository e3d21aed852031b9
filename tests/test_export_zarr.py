"""The zarr export: xarray opens it lazily with labelled coordinates; evaluate reads it."""

from __future__ import annotations

import numpy as np
import pytest
from shared_sessions import N, Written, export_session_of

from m2s2hil.analysis.evaluation.jobs import collect_jobs
from m2s2hil.analysis.evaluation.loading import load_cube, load_truth
from m2s2hil.store.export import ExportError, export_session

xr = pytest.importorskip("xarray")
pytest.importorskip("zarr")


@pytest.fixture
def hubble(shared_sessions) -> Written:
    return export_session_of(shared_sessions)


@pytest.fixture
def iss(shared_sessions) -> Written:
    return export_session_of(shared_sessions, "iss", "B1")


def test_zarr_store_opens_lazily_with_coordinates_and_exact_raws(tmp_path, hubble, iss):
    (a, raws_a), (b, raws_b) = (hubble.open(), hubble.arrays), (iss.open(), iss.arrays)
    out = tmp_path / "all.zarr"
    assert export_session(a, out, "zarr").images == 16
    assert export_session(b, out, "zarr").images == 16  # appended along frame
    with pytest.raises(ExportError, match="already holds session"):
        export_session(a, out, "zarr")
    ds = xr.open_zarr(out, consolidated=False)
    assert ds["raw"].dims == ("frame", "y", "x") and ds.sizes["frame"] == 32
    assert ds["raw"].dtype == np.uint16 and ds["raw"].chunks[0] == (1,) * 32  # one chunk per frame
    assert hasattr(ds["raw"].data, "dask")  # lazy
    assert {"satellite", "build", "elevation", "lighting", "azimuth_deg"} <= set(ds.coords)
    assert ds["wavelength_nm"].values.tolist() == [431, 479, 515, 567, 611, 666, 719, 775, 820, 877]
    assert ds["mosaic_layout"].shape == (4, 4)
    raws = {**raws_a, **raws_b}
    mask = ((ds.satellite == "iss") & (ds.lighting == "directional") & (ds.azimuth_deg == 90.0)).compute()
    sel = ds.where(mask, drop=True)
    assert sel.sizes["frame"] == 2  # E0 and E2
    for i in range(ds.sizes["frame"]):
        assert np.array_equal(ds["raw"][i].values, raws[str(ds["event_id"][i].values)])
    darks = xr.open_zarr(out, group="darks", consolidated=False)
    assert darks.sizes["dark"] == 4
    assert set(ds["dark_key"].values.tolist()) <= set(darks["dark_key"].values.tolist())
    a.close()
    b.close()


def test_evaluate_reads_the_zarr_store_like_the_session(tmp_path, hubble):
    st = hubble.open()
    out = tmp_path / "one.zarr"
    export_session(st, out, "zarr")
    jobs, desc = collect_jobs(out)
    assert len(jobs) == 16 and desc[0].startswith("zarr export")
    from m2s2hil.analysis.evaluation.jobs import session_jobs

    by_id = {j.image_id: j for j in session_jobs(st)}
    for job in jobs[:3]:
        ref = by_id[job.image_id]
        assert job.dark is not None and ref.dark is not None
        assert load_cube(job).tobytes() == load_cube(ref).tobytes()  # same raw, same dark
        assert load_truth(job, (N // 4, N // 4)) is None  # no simulator truth in this session
    st.close()


def _scores(results: dict) -> dict:
    return {seg: {k: v for k, v in r.items() if not k.endswith("time_s")} for seg, r in results.items()}


@pytest.mark.slow  # starts a local Dask cluster
def test_evaluate_and_its_dask_mode_give_the_session_results_from_the_zarr_store(tmp_path, hubble):
    from m2s2hil.analysis.evaluation.evaluate import evaluate_jobs
    from m2s2hil.analysis.evaluation.options import EvalOptions

    st = hubble.open()
    out = tmp_path / "one.zarr"
    export_session(st, out, "zarr")
    zjobs, _ = collect_jobs(out)
    sjobs, _ = collect_jobs(st.path)
    st.close()
    ref = evaluate_jobs(sjobs[:2], EvalOptions(), workers=0)
    local = evaluate_jobs(zjobs[:2], EvalOptions(), workers=0)
    on_dask = evaluate_jobs(zjobs[:2], EvalOptions(), workers=2, processes=False)
    assert on_dask.compute["scheduler"].startswith("inproc://") and not on_dask.errors and not local.errors
    for a, b, c in zip(ref.records, local.records, on_dask.records, strict=True):
        assert a["image_id"] == b["image_id"] == c["image_id"]
        assert _scores(a["results"]) == _scores(b["results"]) == _scores(c["results"])
