"""Studies on simulated data: simulated sessions and the capture-stability (failure) study
(``stability``), the simulator's frames with their ground truth for segmenter benchmarks
(``simframes``) and small synthetic scenes with known labels (``synthetic``).
"""
