"""A stored frame's (or dark's) metadata, built in one place and JSON-encoded once.

The caller (the engine's ``FrameStages.meta`` + processing stage, the importer, a test)
gives what it measured: ``exposure_s``, ``gain``, ``temperature_c``, ``pose``, ``dark_id``,
QC, ... (see ``m2s2hil.engine.frames``). The store adds what only it knows: the session,
the event, provenance and how the frame is stored. The two sets do not overlap: a caller
key the store owns is refused (:class:`MetadataConflict`), never silently replaced.
``exposure_s``, ``gain``, ``dark_id`` and ``bit_depth`` default to the plan's values when the
caller does not give them.

``cube`` records how the frame's cube is obtained: ``{"recipe", "method", "dark_id",
"calibrated", "stored"}``; without a stored cube, ``SessionStore.read_cube`` computes it
from raw + dark (+ calibration) with that recipe (m2s2hil.store.cubes).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from m2s2hil.errors import UsageError
from m2s2hil.plan import CaptureEvent
from m2s2hil.store.frame_files import EncodedJSON, dumps

if TYPE_CHECKING:
    from m2s2hil.store.session import SessionStore

#: Keys the store sets; a caller's metadata must not hold them.
STORE_KEYS = frozenset({
    "session_id", "satellite", "build", "event", "software_version", "rig_digest", "processing_method",
    "storage_format", "cube",
})

#: Version of the cube computation recorded with every frame: ``FrameProcessor(method,
#: camera model, dark = the stored uint16 master, calibration)`` of ``m2s2hil.processing.chain``,
#: float32 ``(bands, H', W')``. Bump it when that computation changes its output.
CUBE_RECIPE = "m2s2hil.processing.chain.FrameProcessor/1"


class MetadataConflict(UsageError):
    """Caller metadata that sets a key the store owns."""

    def __init__(self, keys: list[str]) -> None:
        super().__init__(f"frame metadata key(s) {', '.join(sorted(keys))} are set by the session store, "
                         "not by the caller")


def cube_recipe(method: str, dark_id: str | None, *, calibrated: bool, stored: bool) -> dict[str, Any]:
    """A frame's ``meta["cube"]``: how ``read_cube`` gets its cube (see the module docstring)."""
    return {"recipe": CUBE_RECIPE, "method": method, "dark_id": dark_id, "calibrated": calibrated,
            "stored": stored}


def build_meta(store: SessionStore, event: CaptureEvent, meta: Mapping[str, Any] | None, *,
               cube_stored: bool | None, **defaults: Any) -> tuple[dict[str, Any], EncodedJSON]:
    """(metadata as read back, its JSON text) of a frame (``cube_stored`` given) or a dark
    (``cube_stored=None``) of ``store``. The text is what the TIFF and the journal hold."""
    given = dict(meta or {})
    # A frame's top-level "shape" is the array's, written by frame_files for tifffile.
    clash = sorted((STORE_KEYS | ({"shape"} if cube_stored is not None else set())) & given.keys())
    if clash:
        raise MetadataConflict(clash)
    full: dict[str, Any] = {
        "exposure_s": event.exposure_s,
        "gain": event.gain,
        "dark_id": event.dark_id,
        "bit_depth": store.rig.camera.model.bit_depth,
        **defaults,
        **given,
        "session_id": store.session_id,
        "satellite": store.sweep.satellite,
        "build": store.sweep.build,
        "event": event.model_dump(mode="json"),
        "software_version": store.software_version,
        "rig_digest": store.rig_digest,
        "processing_method": store.sweep.processing,
        "storage_format": store.rig.storage.format,
    }
    if cube_stored is not None:
        full["cube"] = cube_recipe(store.sweep.processing, full.get("dark_id"),
                                   calibrated=given.get("calibration") is not None, stored=cube_stored)
    text = EncodedJSON(dumps(full))
    return json.loads(text), text
