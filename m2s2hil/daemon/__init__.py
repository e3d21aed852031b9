"""The capture daemon's service, apart from HTTP: the session queue, the rig guard and what
they keep on disk (the durable hold). The REST API (:mod:`m2s2hil.api`) sits on top of it;
nothing here imports FastAPI or Starlette."""
