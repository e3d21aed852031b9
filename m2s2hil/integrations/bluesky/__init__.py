"""The rig as bluesky devices (ophyd-async) and an M2S2 sweep as a bluesky plan; the ``bluesky`` extra."""
