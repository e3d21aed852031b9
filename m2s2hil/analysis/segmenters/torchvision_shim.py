"""A stand-in for the four torchvision functions segment-anything 1.0 imports.

segment-anything imports ``resize`` and ``to_pil_image`` (``utils/transforms.py``, resizing
the input so its longest side is the model's) and ``batched_nms`` and ``box_area``
(``automatic_mask_generator.py``) from torchvision without declaring it as a dependency. On
these machines the registry's torchvision is built against CUDA torch: beside the CPU wheel
of torch its C ops do not load and ``import torchvision`` fails. ``ensure_torchvision()``
keeps a torchvision that imports and otherwise registers this module's functions under
torchvision's module names, so segment-anything imports. They follow torchvision's documented
behaviour:

- ``to_pil_image(array)``: an ``(H, W, 3)`` uint8 array as a PIL image;
- ``resize(image, (h, w))``: PIL bilinear resampling (what torchvision does for a PIL image);
- ``box_area(boxes)``: (x2 − x1)·(y2 − y1) of ``(N, 4)`` boxes in (x1, y1, x2, y2);
- ``batched_nms(boxes, scores, idxs, iou_threshold)``: greedy non-maximum suppression per
  category ``idxs``, highest score first, dropping boxes whose IoU with a kept one is greater
  than the threshold; returns the kept indices in decreasing score order.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any

import numpy as np


def to_pil_image(pic: Any) -> Any:
    from PIL import Image

    arr = np.asarray(pic)
    if arr.dtype != np.uint8:
        raise TypeError(f"to_pil_image stand-in takes uint8 arrays, got {arr.dtype}")
    return Image.fromarray(arr)


def resize(img: Any, size: Any) -> Any:
    from PIL import Image

    h, w = (int(size), int(size)) if np.ndim(size) == 0 else (int(size[0]), int(size[1]))
    return img.resize((w, h), Image.Resampling.BILINEAR)


def box_area(boxes: Any) -> Any:
    return (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])


def batched_nms(boxes: Any, scores: Any, idxs: Any, iou_threshold: float) -> Any:
    import torch

    n = int(boxes.shape[0])
    if n == 0:
        return torch.empty((0,), dtype=torch.int64, device=boxes.device)
    b = boxes.detach().to(torch.float64).cpu().numpy()
    # One category never overlaps another: move each category's boxes apart (torchvision's trick).
    b = b + (idxs.detach().cpu().numpy().astype(np.float64) * (float(b.max()) + 1.0))[:, None]
    order = np.argsort(-scores.detach().to(torch.float64).cpu().numpy(), kind="stable")
    b = b[order]
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    suppressed = np.zeros(n, dtype=bool)
    keep = []
    for i in range(n):
        if suppressed[i]:
            continue
        keep.append(i)
        w = np.clip(np.minimum(b[i, 2], b[i + 1:, 2]) - np.maximum(b[i, 0], b[i + 1:, 0]), 0, None)
        h = np.clip(np.minimum(b[i, 3], b[i + 1:, 3]) - np.maximum(b[i, 1], b[i + 1:, 1]), 0, None)
        inter = w * h
        union = area[i] + area[i + 1:] - inter
        iou = np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)
        suppressed[i + 1:] |= iou > iou_threshold
    return torch.as_tensor(order[keep], dtype=torch.int64, device=boxes.device)


def ensure_torchvision() -> str:
    """Import segment-anything: ``"torchvision"`` when the real torchvision imports with its box
    ops, else ``"stand-in"``: segment-anything is imported with the stand-in in place (only the
    names it imports at module level), and the stand-in is then taken out of ``sys.modules``
    again, so that other libraries probing for torchvision (``datasets`` calls
    ``importlib.util.find_spec``) see none rather than a module without a spec."""
    try:
        from torchvision.ops.boxes import batched_nms as _real  # noqa: F401
        from torchvision.transforms.functional import resize as _resize  # noqa: F401

        return "torchvision"
    except Exception:  # ImportError, or the RuntimeError of C ops built for another torch
        pass
    for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
        del sys.modules[name]  # a half-imported real one must not shadow the stand-in
    root = types.ModuleType("torchvision", "m2s2hil stand-in (analysis.segmenters.torchvision_shim)")
    ops, boxes = types.ModuleType("torchvision.ops"), types.ModuleType("torchvision.ops.boxes")
    transforms = types.ModuleType("torchvision.transforms")
    functional = types.ModuleType("torchvision.transforms.functional")
    boxes.batched_nms, boxes.box_area = batched_nms, box_area  # type: ignore[attr-defined]
    functional.resize, functional.to_pil_image = resize, to_pil_image  # type: ignore[attr-defined]
    root.ops, ops.boxes = ops, boxes  # type: ignore[attr-defined]
    root.transforms, transforms.functional = transforms, functional  # type: ignore[attr-defined]
    shim = {"torchvision": root, "torchvision.ops": ops, "torchvision.ops.boxes": boxes,
            "torchvision.transforms": transforms, "torchvision.transforms.functional": functional}
    sys.modules.update(shim)
    try:
        importlib.import_module("segment_anything")  # binds the stand-in's functions at import
    except ModuleNotFoundError as e:
        if e.name != "segment_anything":
            raise  # without segment-anything the callers' own import says so
    finally:
        for name in shim:
            sys.modules.pop(name, None)
    return "stand-in"
