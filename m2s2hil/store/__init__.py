"""Sessions on disk: the session store (``session.py``) and what it is built from (its folder,
journal, records, errors, integrity checks, the catalogue of a data root, size estimates,
frame files and metadata, cubes computed on read), repair, compaction, export and import."""
