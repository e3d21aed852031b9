"""SAM end to end without downloads: a tiny randomly initialised model of SAM's architecture,
saved as a checkpoint file and loaded through the segmenter's real path (strict state-dict
load, segment-anything's automatic mask generator, compositing, band fusion, binary mTC)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from m2s2hil.analysis.errors import AnalysisInputError, SegmenterUnavailableError
from m2s2hil.analysis.evaluation.options import mtc_predictor
from m2s2hil.analysis.metrics.mtc import mtc
from m2s2hil.analysis.segmenters.sam import SamSegmenter
from m2s2hil.analysis.segmenters.sam_model import SamArchitecture, build_sam_architecture
from m2s2hil.analysis.segmenters.torchvision_shim import ensure_torchvision
from m2s2hil.analysis.study.synthetic import synthetic_scene

pytestmark = pytest.mark.slow

# SAM's modules at toy sizes: a 64-pixel input (4 × 4 patches), 16-wide features, one block each.
TINY = SamArchitecture("tiny", encoder_embed_dim=16, encoder_depth=1, encoder_num_heads=2,
                       encoder_global_attn_indexes=(0,), prompt_embed_dim=16, image_size=64, mask_in_chans=4,
                       decoder_depth=1, decoder_mlp_dim=32, decoder_num_heads=2, iou_head_hidden_dim=16)
# A 4 × 4 point grid, and every mask kept: a random model's IoU and stability predictions are noise.
FAST = {"points_per_side": 4, "points_per_batch": 16, "pred_iou_thresh": 0.0, "stability_score_thresh": 0.0}


@pytest.fixture(scope="module")
def torch():
    """torch and segment-anything, imported when a test here runs, not when every worker collects
    (torch alone costs 2-4 s of CPU). Tiny tensors: torch's thread pool costs more than it saves
    (5× the time on a busy 2-core box), so one thread."""
    torch = pytest.importorskip("torch", reason="the sam extra is not installed (pip install 'm2s2hil[sam]')")
    ensure_torchvision()  # segment-anything imports torchvision; the CPU torch wheel has no matching one
    pytest.importorskip("segment_anything.modeling", reason="segment-anything is not installed (sam extra)")
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield torch
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory, torch):
    torch.manual_seed(0)
    model = build_sam_architecture(TINY)
    path = tmp_path_factory.mktemp("sam") / "sam_tiny.pth"
    torch.save(model.state_dict(), path)
    return path, model.state_dict()


@pytest.fixture(scope="module")
def cube():
    return synthetic_scene((48, 48), n_materials=3, noise=0.01, seed=2)[0]


def test_tiny_checkpoint_runs_the_papers_sam_setting_end_to_end(torch, checkpoint, cube):
    path, saved = checkpoint
    seg = SamSegmenter(path, model_type=TINY, generator_options=FAST)
    labels = seg.segment(cube)  # bands 5, 9, 10: auto masks, compositing, aligned majority vote
    assert labels.shape == cube.shape[1:] and labels.dtype == np.int32 and labels.min() >= 0
    loaded = seg._model.state_dict()  # the file's weights, through the real loader
    assert set(loaded) == set(saved) and all(torch.equal(loaded[k], saved[k]) for k in saved)
    # The paper's HIL mTC: top-k = classes per band after de-duplication, binary fusion, integer shifts
    # (K = 3 here, not the paper's 8: the same path at a third of the cost).
    paper = seg.paper_mtc(top_k=4)
    assert paper._model is seg._model and paper.binary and paper.top_k == 4
    binary = paper.segment(cube)
    assert set(np.unique(binary).tolist()) <= {0, 1}
    r = mtc(paper.segment, cube, k=3)
    assert 0.0 <= r.score <= 1.0 and len(r.ious) == 3
    # evaluate's binary mTC predictor is the same setting
    predict, align = mtc_predictor(seg, "sam", "binary", cube.shape[0], n_classes=4)
    assert not align and np.array_equal(predict(cube), binary)


def test_a_checkpoint_of_another_architecture_is_refused_by_name(checkpoint, cube):
    path, _ = checkpoint
    other = SamArchitecture("tiny-wide", 32, 1, 2, (0,), prompt_embed_dim=16, image_size=64, mask_in_chans=4,
                            decoder_depth=1, decoder_mlp_dim=32, decoder_num_heads=2, iou_head_hidden_dim=16)
    with pytest.raises(SegmenterUnavailableError, match="does not fit the tiny-wide architecture"):
        SamSegmenter(path, model_type=other, generator_options=FAST).segment(cube)
    with pytest.raises(AnalysisInputError, match="unknown SAM model 'vit_x'"):
        SamSegmenter(path, model_type="vit_x")
    with pytest.raises(AnalysisInputError, match="generator_options"):
        SamSegmenter(path, model_type=TINY, generator_options={"points_per_sid": 4}).segment(cube)



def test_the_architecture_is_read_off_the_checkpoint(torch, tmp_path, cube):
    """model_type="auto" (the default): every dimension from the file's tensors except the
    decoder's heads, which only reshape (SAM's 8)."""
    from m2s2hil.analysis.segmenters.sam_model import architecture_of

    eight = dataclasses.replace(TINY, name="inferred", decoder_num_heads=8)
    torch.manual_seed(1)
    model = build_sam_architecture(eight)
    path = tmp_path / "sam_tiny8.pth"
    torch.save({"model": model.state_dict()}, path)  # wrapped, as training checkpoints are
    assert architecture_of(model.state_dict()) == eight
    seg = SamSegmenter(path, generator_options=FAST)
    assert seg.model_type == "auto" and seg.architecture is None
    labels = seg.segment(cube)
    assert labels.shape == cube.shape[1:] and seg.architecture == eight
    loaded = seg._model.state_dict()
    assert all(torch.equal(loaded[k], v) for k, v in model.state_dict().items())


def test_the_published_architectures_are_recognised_by_their_shapes(torch):
    """Built on the meta device (shapes, no memory): each reads back as itself, by name."""
    from m2s2hil.analysis.segmenters.sam_model import SAM_ARCHITECTURES, architecture_of

    for name, arch in SAM_ARCHITECTURES.items():
        with torch.device("meta"):
            state = build_sam_architecture(arch).state_dict()
        assert architecture_of(state) is arch, name


def test_a_file_that_is_no_sam_model_says_what_is_missing(torch, tmp_path, cube):
    path = tmp_path / "other.pth"
    torch.save({"fc.weight": torch.zeros(2, 2)}, path)
    with pytest.raises(SegmenterUnavailableError, match="not a SAM model: it has no tensor 'image_encoder"):
        SamSegmenter(path, generator_options=FAST).segment(cube)
    torch.save([1, 2], path)
    with pytest.raises(SegmenterUnavailableError, match="holds a list, not a state dict"):
        SamSegmenter(path, generator_options=FAST).segment(cube)
