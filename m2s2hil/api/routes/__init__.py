"""The REST API's routers, one module per resource: sessions, frames, queue, rig, lens, the
daemon itself (liveness, metrics). Each is added in :func:`m2s2hil.api.app.create_app`."""
