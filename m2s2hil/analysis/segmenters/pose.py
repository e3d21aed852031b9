"""Labelling a frame with the materials of the same pose under diffuse light: ``spectral-pose``
(issue 23, fourteenth pass).

Under one lamp a material's brightness follows each face's angle to the lamp, so its pixels spread
along a curve and split into lit and shadowed groups; a mixture of one Gaussian per material cannot
follow that, and unaided it cannot tell a shadowed silver face from a lit dark-grey one (the
thirteenth pass measured it: trees told the materials label the spotlit frames to within 0.036 of
the diffuse reference, the unsupervised mixture loses 0.09–0.19). A capture session takes every pose
under every lighting at the same stage position, so the session itself can tell the segmenter the
materials: the pose under diffuse light (``POSE_REFERENCE_LIGHTINGS``), segmented by the sweep
segmenter, names them.

``PoseSegmenter.segment(cube)``, after ``use(reference)``:

1. *register*: the translation between the reference's and the frame's log-energy images by OpenCV's
   phase correlation (``cv2.phaseCorrelate``, a Hann window), in whole pixels, leaning to no move
   (``whole_pixels``: the lamp's shading alone moves the estimate by up to 0.66 px). Phase
   correlation keeps only the spectrum's phase, so the two lights' different shading matters less
   than the shared silhouette. On the simulator's spotlit frames it recovers a known shift to within
   0.75 px (0°–80°). A stage that returns to a pose within its repeatability gives a pixel or two; a
   shift beyond ``pose_max_shift_px`` is refused (``PoseRegistrationError``), not trusted;
2. *teach*: the reference's labels, moved by that shift, on the interior of each label (eroded by
   ``pose_erode_px``: a boundary a pixel off is not taught), train gradient-boosted trees
   (scikit-learn's ``HistGradientBoostingClassifier``, ``pose_iterations`` rounds with an L2 leaf
   penalty) on the frame's own features, the sweep
   segmenter's (unit spectrum and 0.1 · log energy), ``pose_sample`` pixels drawn at random;
3. *label*: every pixel of the moved reference's object gets the trees' label; background stays 0.

So the frame's pixels decide each pixel's material and the diffuse frame only names the materials:
where the registration is a pixel off, the trees put the boundary where this frame's pixels put it
(on the simulator's spotlit frames 3 px off: ΔDice −0.001 against −0.164 for the reference's labels
copied; without an offset both are within 0.002 of the reference). The count is the reference's:
a material the reference missed is not found here. A frame with no pose under diffuse light has no
reference and no labels from this segmenter (the evaluation reports why). The figures are in
docs/evaluation.md, "Fourteenth pass".
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from m2s2hil.analysis.arrays import as_cube
from m2s2hil.analysis.errors import AnalysisError, AnalysisInputError

#: the lightings a pose's reference is taken from, the first the session has at that pose: the
#: strong diffuse light (five bars) before the weak one (three), for the signal
POSE_REFERENCE_LIGHTINGS: tuple[str, ...] = ("strong", "weak")
ENERGY_FLOOR = 1e-3  # DN: log energy of a black pixel (the registration image)
MIN_TEACH_PIXELS = 20  # a label whose eroded interior is smaller is taught whole
#: the trees' leaf-weight penalty: without it a reference with a few small parts (Voyager B3, 8
#: materials, 33 taught pixels in its smallest) diverged past 30 rounds: 54 % of the taught pixels
#: labelled right after 50 rounds, against 99 % after 20 (the softmax's curvature on pure leaves)
L2 = 1.0
STILL_PX = 0.75  # a registration below this many pixels is not a move (``whole_pixels``)


class PoseRegistrationError(AnalysisError):
    """The frame and its pose's reference could not be registered within the allowed shift."""


@dataclass(frozen=True)
class PoseReference:
    """What a pose's diffuse frame gives the others: its labels and its image to register against."""

    image_id: str
    labels: np.ndarray  # (H, W) integer, 0 = background
    energy: np.ndarray  # (H, W) log energy (``log_energy``), float16 to keep it small in transit
    time_s: float = 0.0  # the reference's own segmentation time

    @classmethod
    def of(cls, image_id: str, cube: np.ndarray, labels: np.ndarray, time_s: float = 0.0) -> PoseReference:
        arr = as_cube(cube)
        lab = np.asarray(labels)
        if lab.shape != arr.shape[1:]:
            raise AnalysisInputError("labels", f"shape {lab.shape}, expected {arr.shape[1:]} (the cube's)")
        small = np.uint8 if int(lab.max(initial=0)) < 256 else np.uint16
        return cls(image_id, lab.astype(small), log_energy(arr).astype(np.float16), float(time_s))


@dataclass(frozen=True)
class PoseSegmentation:
    labels: np.ndarray
    shift: tuple[int, int]  # (rows, columns) the reference was moved by to meet this frame
    response: float  # phase correlation's peak (1: a pure translation of one image)
    taught: int  # pixels the trees were trained on


def log_energy(cube: np.ndarray) -> np.ndarray:
    """(H, W) float32: log of each pixel's spectral energy (norm over bands)."""
    return np.log(np.maximum(np.linalg.norm(np.asarray(cube, dtype=np.float32), axis=0), ENERGY_FLOOR))


def register(reference: np.ndarray, image: np.ndarray) -> tuple[tuple[float, float], float]:
    """((rows, columns), response): how far ``image`` is moved from ``reference`` (phase correlation
    of the mean-removed images under a Hann window)."""
    a = np.asarray(reference, dtype=np.float32)
    b = np.asarray(image, dtype=np.float32)
    if a.shape != b.shape or a.ndim != 2 or min(a.shape) < 8:
        raise AnalysisInputError("image", f"shape {b.shape} cannot be registered to {a.shape}")
    window = cv2.createHanningWindow((a.shape[1], a.shape[0]), cv2.CV_32F)
    (dx, dy), response = cv2.phaseCorrelate(a - a.mean(), b - b.mean(), window)
    return (float(dy), float(dx)), float(response)


def whole_pixels(shift: float) -> int:
    """``shift`` rounded to whole pixels, but under ``STILL_PX`` read as no move: the lamp's shading
    moves the phase correlation's peak too (up to 0.66 px on the engine's frames of a stage that
    came back exactly), and a stage that did not move is the likelier."""
    return 0 if abs(shift) < STILL_PX else round(shift)


def moved(labels: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``labels`` moved by (dy, dx) whole pixels; what comes in from outside is background."""
    out = np.zeros_like(labels)
    h, w = labels.shape
    if abs(dy) >= h or abs(dx) >= w:
        return out
    src = labels[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)]
    out[max(0, dy):max(0, dy) + src.shape[0], max(0, dx):max(0, dx) + src.shape[1]] = src
    return out


def pose_features(cube: np.ndarray, brightness_weight: float = 0.1) -> np.ndarray:
    """(features, H, W): unit spectra and ``brightness_weight`` · log energy, the sweep segmenter's."""
    arr = np.asarray(cube, dtype=np.float64)
    energy = np.linalg.norm(arr, axis=0)
    unit = arr / np.maximum(energy, 1e-12)
    return np.concatenate([unit, brightness_weight * np.log(np.maximum(energy, 1e-12))[np.newaxis]])


@dataclass
class PoseSegmenter:
    """``spectral-pose``: a frame labelled with its pose's diffuse reference (module docstring)."""

    pose_sample: int = 10_000
    pose_iterations: int = 30
    pose_erode_px: int = 1
    pose_max_shift_px: int = 16
    seed: int = 0
    name: str = "spectral-pose"

    def __post_init__(self) -> None:
        for field, value, low in (("pose_sample", self.pose_sample, 100),
                                  ("pose_iterations", self.pose_iterations, 1),
                                  ("pose_erode_px", self.pose_erode_px, 0),
                                  ("pose_max_shift_px", self.pose_max_shift_px, 0)):
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise AnalysisInputError(field, f"must be a whole number ≥ {low}, got {value!r}")
        self._reference: PoseReference | None = None
        self.last: PoseSegmentation | None = None  # the last frame's registration and labels

    def use(self, reference: PoseReference) -> None:
        """Label the next frames with ``reference`` (a frame of the same pose under diffuse light)."""
        self._reference = reference

    def segment(self, cube: np.ndarray) -> np.ndarray:
        self.last = self.analyse(cube)
        return self.last.labels

    def analyse(self, cube: object) -> PoseSegmentation:
        ref = self._reference
        if ref is None:
            raise AnalysisInputError("reference", "spectral-pose needs its pose's diffuse frame: "
                                     "use(reference) first")
        arr = as_cube(cube)
        if ref.labels.shape != arr.shape[1:]:
            raise AnalysisInputError("cube", f"shape {arr.shape[1:]}, its pose's reference {ref.image_id} is "
                                     f"{ref.labels.shape}")
        (fy, fx), response = register(ref.energy, log_energy(arr))
        dy, dx = whole_pixels(fy), whole_pixels(fx)
        if max(abs(dy), abs(dx)) > self.pose_max_shift_px:
            raise PoseRegistrationError(
                f"this frame is {dy:+d}, {dx:+d} px from its pose's reference {ref.image_id} (more than "
                f"{self.pose_max_shift_px} px: not the same pose, or the stage did not return to it)")
        labels = moved(ref.labels.astype(np.int64), dy, dx)
        obj = labels > 0
        ids = np.unique(labels[obj])
        if ids.size < 2:  # one material or none: the object is all there is to label
            return PoseSegmentation(labels, (dy, dx), response, 0)
        teach = np.zeros_like(obj)
        for i in ids:  # each label's interior: a boundary a pixel off is not taught
            part = labels == i
            inner = (ndimage.binary_erosion(part, iterations=self.pose_erode_px)
                     if self.pose_erode_px else part)
            teach |= inner if inner.sum() >= MIN_TEACH_PIXELS else part
        x = pose_features(arr)
        xs, ys = x[:, teach].T, labels[teach]
        if xs.shape[0] > self.pose_sample:
            pick = np.random.default_rng(self.seed).choice(xs.shape[0], self.pose_sample, replace=False)
            xs, ys = xs[pick], ys[pick]
        if np.unique(ys).size < 2:  # the draw kept one material: it is the answer
            return PoseSegmentation(np.where(obj, ys[0], 0), (dy, dx), response, int(xs.shape[0]))
        from sklearn.ensemble import HistGradientBoostingClassifier

        trees = HistGradientBoostingClassifier(max_iter=self.pose_iterations, early_stopping=False,
                                               l2_regularization=L2, random_state=self.seed).fit(xs, ys)
        out = np.zeros_like(labels)
        out[obj] = trees.predict(x[:, obj].T)
        return PoseSegmentation(out, (dy, dx), response, int(xs.shape[0]))
