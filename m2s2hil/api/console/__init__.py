"""The operator console's side of the API (docs/console.md): its page and plan estimate
(``page.py``), manual control (``manual.py``), the live view (``live.py``), snapshots,
calibration captures, the session browser, the pictures (``pictures.py``: spectra, band
mosaic, coverage map, calibration images), their request and response bodies
(``models.py``) and what they share (``state.py``: live stream, dark library, calibration
path). The static files are ``m2s2hil/console/``."""
