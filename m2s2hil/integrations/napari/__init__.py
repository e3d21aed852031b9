"""An npe2 plugin for napari: opens a session folder or a Zarr export as layers.

The manifest (``napari.yaml``, shipped as package data) is found through the ``napari.manifest``
entry point in pyproject.toml; the reader is :func:`m2s2hil.integrations.napari.reader.get_reader`.
Needs the ``napari`` extra (npe2) to be discovered; napari itself only to show the layers.
"""
