"""The opened rig: its factory, safety operations, mirroring into the simulated world, simulators
served on pseudo-terminals."""
