"""A session replayed as an event-model document stream, and a catalogue in memory that ingests one.

:func:`session_documents` yields ``(name, doc)`` pairs as bluesky's RunEngine would have emitted
them had it run the sweep: ``start`` (the sweep, the camera's bands and FWHM), one descriptor per
stream (``primary`` for the frames, ``dark`` for the master darks), per frame a
``stream_resource`` naming its raw TIFF (``image/tiff``, with its sha256) and a ``stream_datum``
pointing at it, then an ``event`` with the pose read back, exposure, gain, lighting and
temperature; ``stop`` last. Large arrays are never inlined: a consumer (Tiled, databroker, the
:class:`DocumentCatalogue` here) follows the stream resource to the file. Every document is built
by event-model's composers, which validate it against the schemas as they go. Document uids are
derived from the session id (uuid5), so replaying a session twice gives the same run.

:class:`DocumentCatalogue` keeps runs in memory and reads an external array back by following
stream_datum → stream_resource → file; it validates every document it is given, so it doubles as
the check on any document source (the bluesky devices of :mod:`m2s2hil.integrations.bluesky`).
It needs nothing but event-model; a real lab catalogue ingests the same documents in
:mod:`m2s2hil.integrations.tiled` (bluesky's ``TiledWriter`` into a Tiled server).

Needs the ``documents`` extra (event-model).
"""

from __future__ import annotations

import hashlib
import io
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlparse

import event_model
import numpy as np
import tifffile
from event_model import DocumentNames, schema_validators

from m2s2hil.errors import M2S2Error
from m2s2hil.store.session import SessionStore

TIFF = "image/tiff"
_NS = uuid.UUID("0b6f6c3e-6d32-4f59-9a8e-6d2a5c1f2b10")  # this module's uuid5 namespace


class DocumentError(M2S2Error):
    """A document stream that does not hold what a reader needs (a missing resource, a bad sha256)."""


def _uid(*parts: object) -> str:
    return str(uuid.uuid5(_NS, "/".join(map(str, parts))))


def camera_start_metadata(store_or_model: Any) -> dict[str, Any]:
    m = store_or_model.rig.camera.model if hasattr(store_or_model, "rig") else store_or_model
    return {"camera": m.name, "bands_nm": list(m.bands_nm), "fwhm_nm": list(m.fwhm_nm),
            "mosaic_layout": [list(r) for r in m.layout], "bit_depth": m.bit_depth}


def raw_data_key(source: str, height: int, width: int) -> dict[str, Any]:
    """The descriptor's entry for a raw mosaic held in a file (an external ``STREAM:`` key)."""
    return {"source": source, "dtype": "array", "dtype_numpy": "<u2", "shape": [height, width],
            "external": "STREAM:"}


SCALARS: dict[str, tuple[str, str]] = {  # data key -> (event-model dtype, numpy dtype)
    "event_id": ("string", ""), "lighting": ("string", ""), "elevation": ("string", ""),
    "azimuth_deg": ("number", "<f8"), "tilt_deg": ("number", "<f8"),
    "turntable_readback_deg": ("number", "<f8"), "tilt_readback_deg": ("number", "<f8"),
    "exposure_s": ("number", "<f8"), "gain": ("number", "<f8"), "temperature_c": ("number", "<f8"),
}


def _scalar_keys(names: tuple[str, ...]) -> dict[str, Any]:
    # a string key carries no numpy dtype: the schema's pattern wants a size ("|O" has none)
    return {k: {"source": "m2s2hil.store", "dtype": SCALARS[k][0], "shape": [],
                **({"dtype_numpy": SCALARS[k][1]} if SCALARS[k][1] else {})} for k in names}


def _frame_values(meta: dict[str, Any]) -> dict[str, Any]:
    ev = meta.get("event", {})
    pose = meta.get("pose") if isinstance(meta.get("pose"), dict) else {}
    values = {"event_id": ev.get("event_id", meta.get("event_id", "")), "lighting": ev.get("lighting", ""),
              "elevation": ev.get("elevation", ""), "azimuth_deg": ev.get("azimuth_deg"),
              "tilt_deg": ev.get("tilt_deg"), "turntable_readback_deg": pose.get("turntable_deg"),
              "tilt_readback_deg": pose.get("tilt_deg"),
              "exposure_s": meta.get("exposure_s", ev.get("exposure_s")),
              "gain": meta.get("gain", ev.get("gain")), "temperature_c": meta.get("temperature_c")}
    # the schema wants a number for a number key: NaN stands for "not recorded"
    return {k: (float("nan") if v is None and SCALARS[k][0] == "number" else v) for k, v in values.items()}


FRAME_SCALARS = tuple(SCALARS)
DARK_SCALARS = ("event_id", "exposure_s", "gain")


def session_documents(store: SessionStore) -> Iterator[tuple[str, dict[str, Any]]]:
    """The session as documents (see the module docstring), in the order a consumer expects."""
    m = store.rig.camera.model
    frames, darks = store.frames(), store.darks()
    times = [r.time for r in (*frames, *darks)] or [0.0]
    sid = store.session_id
    run = event_model.compose_run(uid=_uid(sid, "start"), time=min(times), metadata={
        "session_id": sid, "plan_name": "m2s2_sweep", "satellite": store.sweep.satellite,
        "build": store.sweep.build, "sweep": store.sweep.model_dump(mode="json"),
        "rig_digest": store.rig_digest, "software_version": store.software_version,
        **camera_start_metadata(store)})
    yield "start", dict(run.start_doc)
    primary = run.compose_descriptor(
        name="primary", uid=_uid(sid, "primary"), time=min(times),
        data_keys={"raw": raw_data_key("m2s2hil.camera", m.height, m.width), **_scalar_keys(FRAME_SCALARS)})
    dark = run.compose_descriptor(
        name="dark", uid=_uid(sid, "dark"), time=min(times),
        data_keys={"master": {**raw_data_key("m2s2hil.darks", m.height, m.width),
                              "dtype_numpy": _dark_dtype(store, darks)},
                   **_scalar_keys(DARK_SCALARS)})
    yield "descriptor", dict(primary.descriptor_doc)
    yield "descriptor", dict(dark.descriptor_doc)
    for seq, d in enumerate(darks, start=1):
        rec = d.files["master"]
        yield from _external(run, dark, store, "master", rec.path, rec.sha256, seq, d.time,
                             {"event_id": d.dark_id, "exposure_s": d.exposure_s, "gain": d.gain})
    for seq, fr in enumerate(frames, start=1):
        rec = fr.files["raw"]
        yield from _external(run, primary, store, "raw", rec.path, rec.sha256, seq, fr.time,
                             {**_frame_values(fr.meta), "event_id": fr.event_id})
    state = store.state
    yield "stop", dict(run.compose_stop(uid=_uid(sid, "stop"), time=max(times),
                                        exit_status="success" if state == "completed" else "abort",
                                        reason="" if state == "completed" else f"session is {state}"))


def _dark_dtype(store: SessionStore, darks: list[Any]) -> str:
    """The numpy dtype of the stream's master darks as their files hold them: uint16 when every
    one is (the compressed format's whole-DN darks), else float32, which holds those exactly too
    (a consumer such as Tiled serves the declared dtype)."""
    for d in darks:
        with tifffile.TiffFile(store.path / d.files["master"].path) as tif:  # the header only
            if tif.pages[0].dtype != np.uint16:
                return "<f4"
    return "<u2"


def _external(run: Any, desc: Any, store: SessionStore, key: str, rel: str, sha256: str, seq: int,
              time: float, values: dict[str, Any]) -> Iterator[tuple[str, dict[str, Any]]]:
    """One event whose ``key`` lives in the file ``rel`` of the session: resource, datum, event."""
    sid = store.session_id
    res = run.compose_stream_resource(mimetype=TIFF, uri=(store.path / rel).resolve().as_uri(), data_key=key,
                                      parameters={"sha256": sha256, "path": rel},
                                      uid=_uid(sid, key, values["event_id"]))
    yield "stream_resource", dict(res.stream_resource_doc)
    datum = res.compose_stream_datum(indices={"start": 0, "stop": 1},
                                     seq_nums={"start": seq, "stop": seq + 1}, descriptor=desc.descriptor_doc)
    yield "stream_datum", dict(datum)
    yield "event", dict(desc.compose_event(data=values, timestamps=dict.fromkeys(values, time), seq_num=seq,
                                           uid=_uid(sid, "event", key, values["event_id"]), time=time))


def read_tiff_resource(resource: dict[str, Any]) -> np.ndarray:
    """The array a ``image/tiff`` stream resource names, checked against its sha256 when given."""
    url = urlparse(resource["uri"])
    if url.scheme != "file":
        raise DocumentError(f"stream resource {resource['uid']}: cannot read {resource['uri']!r}")
    data = Path(unquote(url.path)).read_bytes()
    want = resource.get("parameters", {}).get("sha256")
    if want and hashlib.sha256(data).hexdigest() != want:
        raise DocumentError(f"{resource['uri']}: sha256 does not match its stream resource")
    return np.asarray(tifffile.imread(io.BytesIO(data)))


@dataclass
class Run:
    start: dict[str, Any]
    descriptors: dict[str, dict[str, Any]] = field(default_factory=dict)  # by uid
    events: list[dict[str, Any]] = field(default_factory=list)
    resources: dict[str, dict[str, Any]] = field(default_factory=dict)  # stream resources by uid
    datums: list[dict[str, Any]] = field(default_factory=list)
    stop: dict[str, Any] | None = None

    def stream(self, name: str) -> list[dict[str, Any]]:
        """The events of one stream (``primary``, ``dark``, ...), by seq_num."""
        uids = {u for u, d in self.descriptors.items() if d["name"] == name}
        return sorted((e for e in self.events if e["descriptor"] in uids), key=lambda e: e["seq_num"])

    def read(self, event: dict[str, Any], key: str) -> Any:
        """An event's value of ``key``: inline, or followed to the file its stream datum names."""
        if key in event["data"]:
            return event["data"][key]
        for datum in self.datums:
            res = self.resources[datum["stream_resource"]]
            seqs = datum["seq_nums"]
            if (res["data_key"] == key and datum["descriptor"] == event["descriptor"]
                    and seqs["start"] <= event["seq_num"] < seqs["stop"]):
                if res["mimetype"] != TIFF:
                    raise DocumentError(f"no reader for {res['mimetype']} ({res['uri']})")
                arr = read_tiff_resource(res)
                return arr if datum["indices"]["stop"] - datum["indices"]["start"] == 1 and \
                    seqs["stop"] - seqs["start"] == 1 else arr[event["seq_num"] - seqs["start"]]
        raise DocumentError(f"event {event['uid']} has no {key!r}, inline or by stream datum")


class DocumentCatalogue:
    """Runs in memory, fed as a bluesky callback: ``catalogue(name, doc)``; validates each document."""

    def __init__(self) -> None:
        self.runs: dict[str, Run] = {}
        self._by_descriptor: dict[str, Run] = {}
        self._by_resource: dict[str, Run] = {}
        self.counts: dict[str, int] = {}

    def __call__(self, name: str, doc: dict[str, Any]) -> None:
        schema_validators[DocumentNames(name)].validate(doc)
        self.counts[name] = self.counts.get(name, 0) + 1
        if name == "start":
            self.runs[doc["uid"]] = Run(start=doc)
        elif name == "descriptor":
            run = self._run(doc["run_start"], name)
            run.descriptors[doc["uid"]] = doc
            self._by_descriptor[doc["uid"]] = run
        elif name == "event":
            self._lookup(self._by_descriptor, doc["descriptor"], name).events.append(doc)
        elif name == "stream_resource":
            run = self._run(doc["run_start"], name)
            run.resources[doc["uid"]] = doc
            self._by_resource[doc["uid"]] = run
        elif name == "stream_datum":
            self._lookup(self._by_resource, doc["stream_resource"], name).datums.append(doc)
        elif name == "stop":
            self._run(doc["run_start"], name).stop = doc
        else:
            raise DocumentError(f"this catalogue does not hold {name} documents")

    def _run(self, uid: str, what: str) -> Run:
        return self._lookup(self.runs, uid, what)

    @staticmethod
    def _lookup(table: dict[str, Run], uid: str, what: str) -> Run:
        try:
            return table[uid]
        except KeyError:
            raise DocumentError(f"a {what} document refers to {uid}, which came before no start") from None

    def by(self, **metadata: Any) -> list[Run]:
        """The runs whose start document has these values."""
        return [r for r in self.runs.values() if all(r.start.get(k) == v for k, v in metadata.items())]
