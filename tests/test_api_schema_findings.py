"""What schemathesis' coverage phase found once its per-operation expectations stopped leaking to
every POST (tests/test_api_schema.py): schema-valid requests the daemon refused with 422."""

from __future__ import annotations

from api_support import daemon, small_rig_config, sweep


def test_an_export_the_sessions_state_does_not_allow_is_a_conflict(tmp_path) -> None:
    with daemon(tmp_path / "data", rig_config=small_rig_config(64)) as d:
        assert d.client.post("/queue/hold", json={}).status_code == 200
        queued = d.client.post("/sessions", json=sweep()).json()["session_id"]
        r = d.client.post(f"/sessions/{queued}/export", json={"layout": "m2s2", "overwrite": True})
        assert r.status_code == 409, r.text  # no frame yet: the request is fine, the state is not
        assert "no frames" in r.json()["detail"]
        assert d.client.post("/queue/release", json={}).status_code == 200
        assert d.wait_done(queued)["state"] == "completed"
        assert d.client.post(f"/sessions/{queued}/export", json={"layout": "m2s2"}).status_code == 201
        again = d.client.post(f"/sessions/{queued}/export", json={"layout": "m2s2"})
        assert again.status_code == 409 and "already exists" in again.json()["detail"], again.text
        assert d.client.post(f"/sessions/{queued}/export",
                             json={"layout": "m2s2", "overwrite": True}).status_code == 201
        for loose in ("yes", 1, "true"):  # a flag that destroys an export takes a JSON boolean only
            r = d.client.post(f"/sessions/{queued}/export", json={"layout": "m2s2", "overwrite": loose})
            assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "overwrite"], r.text


def test_darks_need_at_least_one_exposure_and_the_schema_says_so(tmp_path) -> None:
    with daemon(tmp_path / "data", rig_config=small_rig_config(64)) as d:
        doc = d.client.get("/openapi.json").json()
        exposures = doc["components"]["schemas"]["DarksIn"]["properties"]["exposures"]
        assert any(alt.get("minItems") == 1 for alt in exposures.get("anyOf", [exposures])), exposures
        r = d.client.post("/calibration/darks", json={"exposures": [], "lens_capped": True})
        assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "exposures"], r.text
