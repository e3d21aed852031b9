"""The capture engine: the runner, its steps (stop-and-go, continuous), darks, exposure, frame stages,
the capture pipeline, the fault policy, run states and events."""
