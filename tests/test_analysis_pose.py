"""``spectral-pose``: a frame labelled from its pose under diffuse light (segmenters.pose)."""

from __future__ import annotations

import numpy as np
import pytest

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.evaluation.options import EvalOptions, make_segmenter
from m2s2hil.analysis.metrics.scores import score_clusters
from m2s2hil.analysis.segmenters.pose import (
    PoseReference,
    PoseRegistrationError,
    PoseSegmenter,
    moved,
    register,
)
from m2s2hil.analysis.segmenters.registry import create_segmenter
from m2s2hil.errors import UsageError

N = 96
# two materials of one brightness and different spectra (a slope each way over ten bands)
SPECTRA = {1: np.linspace(1.0, 0.4, 10), 2: np.linspace(0.4, 1.0, 10)}


def scene(shading: np.ndarray | None = None, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(cube, truth): a plate of material 1 with an L of material 2 on a dark background."""
    truth = np.zeros((N, N), np.int64)
    truth[20:76, 18:80] = 1
    truth[30:70, 30:44] = 2
    truth[56:70, 30:66] = 2
    cube = np.full((10, N, N), 2.0)
    for m, s in SPECTRA.items():
        cube[:, truth == m] = 300.0 * s[:, None]
    if shading is not None:  # one lamp: brightness follows the face, not the material
        cube[:, truth > 0] *= shading[truth > 0]
    cube += np.random.default_rng(seed).normal(0, 1.5, cube.shape)
    return np.maximum(cube, 0).astype(np.float32), truth


def spotlit() -> np.ndarray:
    yy, xx = np.mgrid[0:N, 0:N]
    return 0.05 + 0.95 * np.clip((xx - 10) / 80, 0, 1) * np.clip((yy + 10) / 60, 0, 1)


def shifted(cube: np.ndarray, truth: np.ndarray, dy: int, dx: int) -> tuple[np.ndarray, np.ndarray]:
    return np.roll(cube, (dy, dx), axis=(1, 2)), moved(truth, dy, dx)


def test_register_finds_a_known_translation_between_two_lights() -> None:
    diffuse, _ = scene()
    lit, _ = scene(spotlit(), seed=1)
    from m2s2hil.analysis.segmenters.pose import log_energy

    for dy, dx in ((0, 0), (2, -3), (-5, 4)):
        (fy, fx), response = register(log_energy(diffuse), log_energy(np.roll(lit, (dy, dx), axis=(1, 2))))
        assert (round(fy), round(fx)) == (dy, dx)
        assert 0 < response <= 1


def test_a_spotlit_frame_a_few_pixels_off_is_labelled_by_its_own_pixels() -> None:
    diffuse, truth = scene()
    ref = PoseReference.of("weak/E1/az000/f0", diffuse, truth)
    assert ref.labels.dtype == np.uint8 and ref.energy.dtype == np.float16
    lit, lit_truth = shifted(*scene(spotlit(), seed=2), 2, -3)
    seg = PoseSegmenter(pose_sample=2000)
    seg.use(ref)
    found = seg.analyse(lit)
    assert found.shift == (2, -3) and found.taught > 0
    pose_dice = score_clusters(lit_truth, found.labels)[0].macro_dice
    copied_dice = score_clusters(lit_truth, truth)[0].macro_dice  # the reference's labels, unmoved
    assert pose_dice > 0.97 > copied_dice + 0.05
    assert set(np.unique(found.labels)) == {0, 1, 2}
    assert np.array_equal(seg.segment(lit), found.labels) and seg.last is not None


def test_materials_told_apart_only_by_spectrum_survive_the_shading() -> None:
    # brightness alone would mislabel: the shading spans 20 x, the materials are equally bright
    diffuse, truth = scene()
    lit, _ = scene(spotlit(), seed=3)
    seg = PoseSegmenter(pose_sample=2000)
    seg.use(PoseReference.of("ref", diffuse, truth))
    labels = seg.segment(lit)
    assert (labels[truth == 2] == 2).mean() > 0.97 and (labels[truth == 1] == 1).mean() > 0.97


def test_a_frame_of_another_pose_is_refused_not_trusted() -> None:
    diffuse, truth = scene()
    lit, _ = scene(spotlit(), seed=4)
    seg = PoseSegmenter(pose_max_shift_px=4)
    seg.use(PoseReference.of("weak/E1/az010/f0", diffuse, truth))
    with pytest.raises(PoseRegistrationError,
                       match=r"\+0, \+9 px from its pose's reference weak/E1/az010/f0"):
        seg.segment(np.roll(lit, 9, axis=2))


def test_one_material_is_the_moved_object() -> None:
    diffuse, truth = scene()
    one = (truth > 0).astype(np.int64)
    seg = PoseSegmenter()
    seg.use(PoseReference.of("ref", diffuse, one))
    found = seg.analyse(np.roll(diffuse, (1, 2), axis=(1, 2)))
    assert found.shift == (1, 2) and found.taught == 0
    assert np.array_equal(found.labels, moved(one, 1, 2))


def test_moved_fills_with_background() -> None:
    lab = np.arange(1, 13).reshape(3, 4)
    assert moved(lab, 1, -1).tolist() == [[0, 0, 0, 0], [2, 3, 4, 0], [6, 7, 8, 0]]
    assert moved(lab, 0, 0).tolist() == lab.tolist()
    assert not moved(lab, 3, 0).any()


def test_bad_input_gets_typed_errors() -> None:
    diffuse, truth = scene()
    with pytest.raises(AnalysisInputError, match="use\\(reference\\) first"):
        PoseSegmenter().segment(diffuse)
    seg = PoseSegmenter()
    seg.use(PoseReference.of("weak/E0/az000/f0", diffuse, truth))
    with pytest.raises(AnalysisInputError, match=r"its pose's reference weak/E0/az000/f0 is \(96, 96\)"):
        seg.segment(diffuse[:, :64, :64])
    with pytest.raises(AnalysisInputError, match="labels: shape"):
        PoseReference.of("x", diffuse, truth[:10])
    for bad in ({"pose_sample": 0}, {"pose_iterations": True}, {"pose_max_shift_px": -1},
                {"pose_erode_px": 1.5}):
        with pytest.raises(AnalysisInputError, match=next(iter(bad))):
            PoseSegmenter(**bad)


def test_the_registry_gives_each_segmenter_its_own_options() -> None:
    seg = create_segmenter("spectral-pose", pose_sample=500, seed=3, brightness_weight=0.2)
    assert isinstance(seg, PoseSegmenter) and seg.pose_sample == 500 and seg.seed == 3
    # the evaluation's options go to every segmenter: the pose ones to spectral-pose alone
    sweep = make_segmenter("spectral-sweep", {"pose_sample": 500, "max_materials": 6})
    assert sweep.frame.max_materials == 6  # type: ignore[attr-defined]
    with pytest.raises(UsageError, match="--also spectral-pose"):
        EvalOptions(multi="spectral-pose")


@pytest.mark.slow  # two 1024² renders and a sweep fit
def test_a_reference_with_small_parts_is_followed_not_diverged_from() -> None:
    # Voyager B3 (8 materials, the smallest taught 33 pixels) at 240° under the spotlight: unpenalised,
    # the trees diverged past 30 rounds and agreed with the reference on 47 % of the object.
    from sim_frame import one_frame

    from m2s2hil.analysis.segmenters.sweep import SweepSegmenter

    diffuse = one_frame("voyager", "B3", size=1024, azimuths=[240.0])
    lit = one_frame("voyager", "B3", size=1024, azimuths=[240.0], lightings=["directional"],
                    spot_angle_deg=45.0)
    found = SweepSegmenter().analyse_sweep([diffuse.cube], [diffuse.exposure_s], [diffuse.band_saturated])
    ref = found[0].labels
    assert np.unique(ref[ref > 0]).size >= 7
    seg = PoseSegmenter(pose_iterations=50)
    seg.use(PoseReference.of("weak", diffuse.cube, ref))
    labels = seg.segment(lit.cube)
    assert (labels == ref)[ref > 0].mean() > 0.8
    assert score_clusters(lit.gt, labels)[0].macro_dice > score_clusters(diffuse.gt, ref)[0].macro_dice - 0.05
