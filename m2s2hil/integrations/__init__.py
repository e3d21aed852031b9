"""Bridges to the tools labs already use: ENVI files (Spectral Python), event-model documents
(bluesky, Tiled, databroker), a napari reader, and the rig as bluesky devices.

Each bridge lives in its own module or subpackage and imports its library only there, so a
capture-only install (none of the extras) never imports any of them. They read and write
sessions only through the session store's public API, and drive the rig only through the
opened rig's drivers (:mod:`m2s2hil.rig.opened`).
"""
