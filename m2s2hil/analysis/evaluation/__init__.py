"""Evaluating segmenters over sessions and exported datasets (the paper's section 3): the
images to evaluate (``jobs``), their pixels (``loading``), the run's options (``options``),
the driver (``evaluate``) on Dask (``parallel``), and the per-image rows and Table 2 built
from its records (``aggregates``, ``table2``). The files are written by ``analysis.report``.
"""
