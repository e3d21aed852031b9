"""A SAM model from a checkpoint file: its architecture by name, the weights loaded strictly.

``SAM_ARCHITECTURES`` holds the three published image encoders with the dimensions of
segment-anything 1.0's ``build_sam.py`` (ViT-H: 1280 wide, 32 blocks, 16 heads, global
attention in blocks 7, 15, 23, 31; ViT-L: 1024, 24, 16, 5/11/17/23; ViT-B: 768, 12, 12,
2/5/8/11; all with a 256-wide prompt space, 1024-pixel input, 16-pixel patches, windows of 14,
a two-block two-way decoder with 2048-wide MLPs and 8 heads). Any other ``SamArchitecture`` is
built the same way, which is how the tests run the whole path on a tiny randomly initialised
model without downloading weights.

``build_sam_model`` differs from segment-anything's own builder in three ways, each on
purpose: ``torch.load(..., map_location=device, weights_only=True)`` (a checkpoint saved on
a GPU opens on a CPU; a checkpoint cannot run code when it is opened), a strict load whose
failure names the file and the architecture (a ViT-B file given as ViT-H), and the model moved
to ``device`` in eval mode.

segment-anything imports two things from torchvision (resizing an image, box non-maximum
suppression) but does not declare it; the registry's torchvision is built against CUDA torch
and its C ops do not load beside the CPU wheel (``RuntimeError: operator torchvision::nms does
not exist``). ``torchvision_shim.ensure_torchvision`` puts a stand-in for those functions in
place when the real one does not import.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

from m2s2hil.analysis.errors import SegmenterUnavailableError
from m2s2hil.analysis.segmenters.torchvision_shim import ensure_torchvision


@dataclass(frozen=True)
class SamArchitecture:
    """The dimensions that make a SAM model (names as in segment-anything's modules)."""

    name: str
    encoder_embed_dim: int
    encoder_depth: int
    encoder_num_heads: int
    encoder_global_attn_indexes: tuple[int, ...]
    prompt_embed_dim: int = 256
    image_size: int = 1024
    patch_size: int = 16
    window_size: int = 14
    mask_in_chans: int = 16
    decoder_depth: int = 2
    decoder_mlp_dim: int = 2048
    decoder_num_heads: int = 8
    iou_head_depth: int = 3
    iou_head_hidden_dim: int = 256


SAM_ARCHITECTURES: dict[str, SamArchitecture] = {
    "vit_h": SamArchitecture("vit_h", 1280, 32, 16, (7, 15, 23, 31)),
    "vit_l": SamArchitecture("vit_l", 1024, 24, 16, (5, 11, 17, 23)),
    "vit_b": SamArchitecture("vit_b", 768, 12, 12, (2, 5, 8, 11)),
}
# The image normalisation SAM was trained with (ImageNet's mean and SD in 0..255).
PIXEL_MEAN = (123.675, 116.28, 103.53)
PIXEL_STD = (58.395, 57.12, 57.375)


def build_sam_architecture(arch: SamArchitecture) -> Any:
    """An untrained ``segment_anything.modeling.Sam`` of ``arch`` (needs torch and segment-anything)."""
    import torch

    ensure_torchvision()  # importing segment_anything.modeling runs the package's __init__, which needs it
    from segment_anything.modeling import ImageEncoderViT, MaskDecoder, PromptEncoder, Sam, TwoWayTransformer

    grid = arch.image_size // arch.patch_size
    return Sam(
        image_encoder=ImageEncoderViT(
            depth=arch.encoder_depth, embed_dim=arch.encoder_embed_dim, img_size=arch.image_size, mlp_ratio=4,
            norm_layer=partial(torch.nn.LayerNorm, eps=1e-6), num_heads=arch.encoder_num_heads,
            patch_size=arch.patch_size, qkv_bias=True, use_rel_pos=True,
            global_attn_indexes=arch.encoder_global_attn_indexes, window_size=arch.window_size,
            out_chans=arch.prompt_embed_dim,
        ),
        prompt_encoder=PromptEncoder(
            embed_dim=arch.prompt_embed_dim, image_embedding_size=(grid, grid),
            input_image_size=(arch.image_size, arch.image_size), mask_in_chans=arch.mask_in_chans,
        ),
        mask_decoder=MaskDecoder(
            num_multimask_outputs=3,
            transformer=TwoWayTransformer(depth=arch.decoder_depth, embedding_dim=arch.prompt_embed_dim,
                                          mlp_dim=arch.decoder_mlp_dim, num_heads=arch.decoder_num_heads),
            transformer_dim=arch.prompt_embed_dim, iou_head_depth=arch.iou_head_depth,
            iou_head_hidden_dim=arch.iou_head_hidden_dim,
        ),
        pixel_mean=list(PIXEL_MEAN),
        pixel_std=list(PIXEL_STD),
    )


def build_sam_model(arch: SamArchitecture, checkpoint: str | Path, device: str = "cpu") -> Any:
    """``arch`` with the weights of ``checkpoint`` (a state dict saved by ``torch.save``), on ``device``."""
    import torch

    path = Path(checkpoint)
    model = build_sam_architecture(arch)
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # not a torch file, truncated, or holding more than tensors
        raise SegmenterUnavailableError("sam", f"cannot read checkpoint {path}: {exc}") from exc
    if isinstance(state, dict) and "model" in state and isinstance(state["model"], dict):
        state = state["model"]  # a training checkpoint that wraps the state dict
    try:
        model.load_state_dict(state, strict=True)
    except (RuntimeError, TypeError, AttributeError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SegmenterUnavailableError(
            "sam", f"checkpoint {path} does not fit the {arch.name} architecture ({first}); "
                   "pass the model_type the weights were trained as") from exc
    return model.to(device=device).eval()
