"""Scores of a segmentation: per-class and macro precision, recall, Dice and micro-IoU
(``scores``), the ground-truth-free translation consistency mTC (``mtc``, which runs a
segmenter's fused band predictions) and the paired significance test (``significance``).
"""
