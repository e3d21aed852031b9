"""Sessions on disk: the session store, its journal, atomic files, frame files, export and import."""
