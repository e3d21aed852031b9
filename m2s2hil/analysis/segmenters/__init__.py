"""Segmenters: the ``Segmenter`` protocol and its registry (``registry``), the default
``spectral`` segmenter, the optional ``sam`` baseline and its mask compositing and label-map
fusion (``compositing``), and the RGB baseline that wraps any of them (``rgb``).

Below the metrics: a segmenter never imports a score.
"""
