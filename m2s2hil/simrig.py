"""The simulated rig (see :mod:`m2s2hil.rig_factory`)."""

from m2s2hil.rig_factory import build_simulators, open_rig, open_simulated_rig

__all__ = ["build_simulators", "open_rig", "open_simulated_rig"]
