"""The API's defences (docs/security.md): token and listening rules (``security.py``), the
cross-site guard (``csrf.py``), the Host allow-list (``hosts.py``), log-safe text
(``logsafe.py``)."""
