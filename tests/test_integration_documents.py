"""A session replayed as event-model documents, validated, ingested in memory, a frame read back exactly."""

from __future__ import annotations

import numpy as np
import pytest
from shared_sessions import export_session_of

pytest.importorskip("event_model", reason="the documents extra (event-model) is not installed")

from event_model import DocumentNames, schema_validators

from m2s2hil.integrations.documents import DocumentCatalogue, DocumentError, session_documents


@pytest.fixture
def hubble(shared_sessions):
    return export_session_of(shared_sessions)


def test_documents_are_valid_and_in_order(hubble):
    with hubble.open() as st:
        docs = list(session_documents(st))
        n_frames, n_darks = len(st.frames()), len(st.darks())
        bands = list(st.rig.camera.model.bands_nm)
    names = [n for n, _ in docs]
    assert names[0] == "start" and names[-1] == "stop" and names[1:3] == ["descriptor", "descriptor"]
    for name, doc in docs:
        schema_validators[DocumentNames(name)].validate(doc)
    assert names.count("event") == names.count("stream_datum") == n_frames + n_darks
    assert names.count("stream_resource") == n_frames + n_darks
    start = docs[0][1]
    assert start["session_id"] == hubble.session_id and start["bands_nm"] == bands
    primary = docs[1][1]
    assert primary["name"] == "primary" and primary["data_keys"]["raw"]["external"] == "STREAM:"
    # a stream key is never inlined in an event
    assert all("raw" not in d["data"] for n, d in docs if n == "event")
    # replaying twice gives the same run (uids derive from the session)
    with hubble.open() as st:
        again = list(session_documents(st))
    assert [d["uid"] for n, d in again if "uid" in d] == [d["uid"] for n, d in docs if "uid" in d]


def test_catalogue_reads_every_frame_back_exactly(hubble):
    cat = DocumentCatalogue()
    with hubble.open() as st:
        for name, doc in session_documents(st):
            cat(name, doc)
        run, = cat.by(session_id=hubble.session_id)
        events = run.stream("primary")
        assert len(events) == len(hubble.arrays) == 16
        for ev in events:
            raw = run.read(ev, "raw")
            assert raw.dtype == np.uint16
            assert np.array_equal(raw, hubble.arrays[ev["data"]["event_id"]])
            fr = st.frame(ev["data"]["event_id"])
            assert ev["data"]["lighting"] == fr.meta["event"]["lighting"]
            assert ev["data"]["turntable_readback_deg"] == fr.meta["pose"]["turntable_deg"]
        dark_ev = run.stream("dark")[0]
        assert np.array_equal(run.read(dark_ev, "master"), st.load_dark(dark_ev["data"]["event_id"]))
    assert run.stop is not None and run.stop["num_events"] == {"primary": 16, "dark": 2}


def test_a_changed_file_is_refused(tmp_path, hubble):
    copy = hubble.copy_to(tmp_path)
    cat = DocumentCatalogue()
    with copy.open() as st:
        for name, doc in session_documents(st):
            cat(name, doc)
        first = st.frames()[0]
        path = st.path / first.files["raw"].path
    data = path.read_bytes()
    path.write_bytes(data[:-1] + bytes([data[-1] ^ 0xFF]))  # a changed byte, whatever it was
    run, = cat.runs.values()
    ev = next(e for e in run.stream("primary") if e["data"]["event_id"] == first.event_id)
    with pytest.raises(DocumentError, match="sha256"):
        run.read(ev, "raw")


def test_catalogue_refuses_an_invalid_or_orphan_document():
    cat = DocumentCatalogue()
    with pytest.raises(Exception, match="required"):
        cat("start", {"time": 1.0})  # no uid
    with pytest.raises(DocumentError, match="no start"):
        cat("stop", {"uid": "s", "time": 1.0, "run_start": "nope", "exit_status": "success"})
