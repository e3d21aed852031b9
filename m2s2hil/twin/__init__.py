"""The digital twin of the rig: the paper's synthetic domain at the session's poses, the
mockup's registration to the captured frames, checks during the sweep, and labels for HIL frames."""
