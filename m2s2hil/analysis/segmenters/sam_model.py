"""A SAM model from a checkpoint file: its architecture by name, the weights loaded strictly.

``SAM_ARCHITECTURES`` holds the three published image encoders with the dimensions of
segment-anything 1.0's ``build_sam.py`` (ViT-H: 1280 wide, 32 blocks, 16 heads, global
attention in blocks 7, 15, 23, 31; ViT-L: 1024, 24, 16, 5/11/17/23; ViT-B: 768, 12, 12,
2/5/8/11; all with a 256-wide prompt space, 1024-pixel input, 16-pixel patches, windows of 14,
a two-block two-way decoder with 2048-wide MLPs and 8 heads). Any other ``SamArchitecture`` is
built the same way, which is how the tests run the whole path on a tiny randomly initialised
model without downloading weights.

``architecture_of`` reads the architecture off a checkpoint's tensors (``model_type="auto"``, the
segmenter's default): the encoder's width from the patch embedding, its depth from the block
count, its heads from the relative-position tables' width, its global-attention blocks from their
length (2·grid − 1 against 2·window − 1), the input size from the position embedding and the
decoder's from its layers. Only the decoder's head count is not in the weights (it only reshapes);
all three published models use 8, and so does an inferred one.

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

import dataclasses
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


def _count(state: dict[str, Any], prefix: str) -> int:
    """How many numbered children ``prefix.<i>.`` the state dict holds."""
    found = {k[len(prefix):].split(".", 1)[0] for k in state if k.startswith(prefix)}
    return len({int(i) for i in found if i.isdigit()})


def architecture_of(state: dict[str, Any], source: str = "checkpoint") -> SamArchitecture:
    """The architecture whose modules have the shapes of ``state`` (a SAM state dict): a published
    one by name when every dimension matches it, else one named ``"inferred"``; a
    ``SegmenterUnavailableError`` naming the missing tensor when ``state`` is not a SAM model."""

    def shape(key: str) -> tuple[int, ...]:
        if key not in state or not hasattr(state[key], "shape"):
            raise SegmenterUnavailableError("sam", f"{source} is not a SAM model: it has no tensor {key!r}")
        return tuple(int(d) for d in state[key].shape)

    width, _, patch, _ = shape("image_encoder.patch_embed.proj.weight")
    grid = shape("image_encoder.pos_embed")[1]
    depth = _count(state, "image_encoder.blocks.")
    if depth == 0:
        raise SegmenterUnavailableError("sam", f"{source} is not a SAM model: its encoder has no blocks")
    tables = [shape(f"image_encoder.blocks.{i}.attn.rel_pos_h") for i in range(depth)]
    head_dim = tables[0][1]
    global_blocks = tuple(i for i, (n, _) in enumerate(tables) if n == 2 * grid - 1)
    windows = {(n + 1) // 2 for n, _ in tables if n != 2 * grid - 1}
    prompt = shape("image_encoder.neck.0.weight")[0]
    iou_depth = _count(state, "mask_decoder.iou_prediction_head.layers.")
    found = SamArchitecture(
        "inferred", encoder_embed_dim=width, encoder_depth=depth, encoder_num_heads=max(1, width // head_dim),
        encoder_global_attn_indexes=global_blocks, prompt_embed_dim=prompt, image_size=grid * patch,
        patch_size=patch, window_size=windows.pop() if len(windows) == 1 else 14,
        mask_in_chans=shape("prompt_encoder.mask_downscaling.3.weight")[0],
        decoder_depth=_count(state, "mask_decoder.transformer.layers."),
        decoder_mlp_dim=shape("mask_decoder.transformer.layers.0.mlp.lin1.weight")[0],
        iou_head_depth=iou_depth,
        iou_head_hidden_dim=shape("mask_decoder.iou_prediction_head.layers.0.weight")[0],
    )
    for known in SAM_ARCHITECTURES.values():
        if dataclasses.replace(known, name="inferred") == found:
            return known
    return found


def read_checkpoint(checkpoint: str | Path, device: str = "cpu") -> dict[str, Any]:
    """The state dict of a checkpoint file (unwrapped from a training checkpoint's ``"model"``)."""
    import torch

    path = Path(checkpoint)
    try:
        state = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # not a torch file, truncated, or holding more than tensors
        raise SegmenterUnavailableError("sam", f"cannot read checkpoint {path}: {exc}") from exc
    if isinstance(state, dict) and "model" in state and isinstance(state["model"], dict):
        state = state["model"]  # a training checkpoint that wraps the state dict
    if not isinstance(state, dict):
        what = type(state).__name__
        raise SegmenterUnavailableError("sam", f"checkpoint {path} holds a {what}, not a state dict")
    return state


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


def build_sam_model(arch: SamArchitecture | None, checkpoint: str | Path, device: str = "cpu"
                    ) -> tuple[Any, SamArchitecture]:
    """``arch`` (``None``: read off the checkpoint, :func:`architecture_of`) with the weights of
    ``checkpoint`` (a state dict saved by ``torch.save``), on ``device``; returns the model and
    the architecture it was built as."""
    path = Path(checkpoint)
    state = read_checkpoint(path, device)
    if arch is None:
        arch = architecture_of(state, f"checkpoint {path}")
    model = build_sam_architecture(arch)
    try:
        model.load_state_dict(state, strict=True)
    except (RuntimeError, TypeError, AttributeError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SegmenterUnavailableError(
            "sam", f"checkpoint {path} does not fit the {arch.name} architecture ({first}); "
                   "pass the model_type the weights were trained as, or 'auto'") from exc
    return model.to(device=device).eval(), arch
