"""A session ingested into Tiled by bluesky's own ``TiledWriter``, the way a beamline's runs are.

:func:`ingest_session` feeds :func:`~m2s2hil.integrations.documents.session_documents` to
:class:`bluesky.callbacks.tiled_writer.TiledWriter` over a Tiled client: the run becomes a
``BlueskyRun`` container keyed by its start uid, each stream a container with its scalars as an
``internal`` table and its raw mosaics (``primary/raw``) or master darks (``dark/master``) as an
array over the session's own TIFF files, registered in place (``management: external``:
nothing is copied, so the server must be allowed to read the data root: ``readable_storage``).

One piece is ours: bluesky's consolidators know TIFF *sequences* (one stream resource whose
filename template counts frames), while a session names each frame's file by its event id, so
the replay gives every frame its own ``image/tiff`` stream resource. :class:`FileTIFFConsolidator`
joins those files, in event order, into the standard TIFF-sequence data source that Tiled's
``TiffSequenceAdapter`` serves; it goes into bluesky's ``CONSOLIDATOR_REGISTRY`` (its documented
extension point) under ``image/tiff``, a key bluesky leaves empty. Nothing on the server side
is custom: any Tiled server with write access and ``readable_storage`` over the data root can
ingest a session.

Needs the ``tiled`` extra (``tiled[server]`` for a server in-process, as the tests start one).
"""

from __future__ import annotations

from typing import Any

from bluesky.callbacks.tiled_writer import TiledWriter
from bluesky.consolidators import CONSOLIDATOR_REGISTRY, Asset, ConsolidatorBase

from m2s2hil.integrations.documents import TIFF, session_documents
from m2s2hil.store.session import SessionStore

#: The mimetype of a stack of single-frame TIFF files, as Tiled serves it.
TIFF_SEQUENCE = "multipart/related;type=image/tiff"


class FileTIFFConsolidator(ConsolidatorBase):
    """One data key's frames, one TIFF file per stream resource, stacked in the order they come."""

    supported_mimetypes: set[str] = {TIFF}  # noqa: RUF012 (bluesky's base declares it so)
    join_method = "stack"

    def __init__(self, stream_resource: Any, descriptor: Any) -> None:
        super().__init__(stream_resource, descriptor)
        self.mimetype = TIFF_SEQUENCE  # what the server reads: the list of files, one frame each
        self.chunk_shape = (1,)  # a file is one chunk of one frame
        self._uris = {stream_resource["uid"]: stream_resource["uri"]}

    def update_from_stream_resource(self, stream_resource: Any) -> None:
        if stream_resource["mimetype"] != TIFF:
            raise ValueError(f"stream resource {stream_resource['uid']}: {stream_resource['mimetype']} "
                             f"in a stack of {TIFF} files")
        self._uris[stream_resource["uid"]] = stream_resource["uri"]

    def consume_stream_datum(self, doc: Any) -> None:
        n = doc["indices"]["stop"] - doc["indices"]["start"]
        if n != 1:
            raise ValueError(f"stream datum {doc['uid']}: {n} frames in one single-frame TIFF file")
        self.assets.append(Asset(data_uri=self._uris[doc["stream_resource"]], is_directory=False,
                                 parameter="data_uris", num=len(self.assets) + 1))
        # the row of each seq_num in the stacked array (the base class counts within one resource)
        first = doc["seq_nums"]["start"]
        self._seqnums_to_indices_map[first] = self._num_rows
        self._num_rows += 1


def register_consolidator() -> None:
    """Put :class:`FileTIFFConsolidator` in bluesky's registry (idempotent; never replaces
    a consolidator someone else registered for ``image/tiff``)."""
    if TIFF not in CONSOLIDATOR_REGISTRY:
        CONSOLIDATOR_REGISTRY[TIFF] = FileTIFFConsolidator


def ingest_session(store: SessionStore, client: Any) -> str:
    """Write the session's documents into the Tiled container ``client``; returns the run's key
    (its start document's uid)."""
    register_consolidator()
    writer = TiledWriter(client)
    uid = ""
    for name, doc in session_documents(store):
        if name == "start":
            uid = doc["uid"]
        writer(name, doc)
    return uid
