"""The opened rig: its device kinds (``devices/``, one registry entry per protocol), its factory,
safety operations, mirroring into the simulated world, simulators served on pseudo-terminals."""
