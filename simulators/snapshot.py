"""Pictures of simulated frames for people: a false-colour PNG and a label-map PNG.

The false colour comes from the super-pixel cube (one value per band per MSFA cell,
duplicated positions averaged), three bands near 650 / 550 / 470 nm shown as R / G /
B after dark subtraction, white balance by the band responses, a shared percentile
stretch and a display gamma.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

# Display colours of the filaments (close to how each looks), fixed across images.
PALETTE: dict[str, tuple[int, int, int]] = {
    "background": (0, 0, 0),
    "pro_silver": (190, 192, 200),
    "dark_grey": (75, 75, 80),
    "pro_metallic_blue": (35, 70, 205),
    "pro_gold": (215, 175, 50),
    "cold_white": (250, 250, 255),
    "pro_metallic_magenta": (205, 35, 165),
    "red": (225, 30, 30),
    "azure_blue": (60, 175, 245),
    "olive_brown": (115, 100, 35),
    "lime_green": (140, 230, 40),
    "wood": (185, 135, 85),
}


def colour_of(name: str) -> tuple[int, int, int]:
    if name in PALETTE:
        return PALETTE[name]
    h = hashlib.sha256(name.encode()).digest()
    return (64 + h[0] % 192, 64 + h[1] % 192, 64 + h[2] % 192)


def superpixel(mosaic: np.ndarray, layout: Sequence[Sequence[int]], n_bands: int | None = None) -> np.ndarray:
    """(n_bands, H/n, W/n) float32: each band's value per n × n cell (duplicates averaged)."""
    lay = np.asarray(layout)
    n = lay.shape[0]
    nb = int(lay.max()) + 1 if n_bands is None else n_bands
    h, w = mosaic.shape
    if h % n or w % n:
        raise ValueError(f"mosaic {w}x{h} is not a multiple of the {n}x{n} MSFA period")
    cube = np.zeros((nb, h // n, w // n), dtype=np.float32)
    count = np.zeros(nb, dtype=np.float32)
    for i in range(n):
        for j in range(n):
            b = int(lay[i, j])
            cube[b] += mosaic[i::n, j::n]
            count[b] += 1
    if np.any(count == 0):
        raise ValueError(f"layout has no position for bands {np.flatnonzero(count == 0).tolist()}")
    return cube / count[:, None, None]


def rgb_bands(
    bands_nm: Sequence[float], targets_nm: Sequence[float] = (650.0, 550.0, 470.0)
) -> tuple[int, ...]:
    """Indices of the bands nearest the R, G, B target wavelengths."""
    b = np.asarray(bands_nm, dtype=float)
    return tuple(int(np.argmin(np.abs(b - t))) for t in targets_nm)


def false_colour(
    cube: np.ndarray, bands: Sequence[int], white: Sequence[float] | None = None, percentile: float = 99.5,
    gamma: float = 2.2,
) -> np.ndarray:
    """(h, w, 3) uint8 from three bands of a dark-subtracted cube.

    ``white`` = per-band response to a white diffuser (divides it out). The stretch is
    shared by the three channels so the colours keep their ratios.
    """
    rgb = np.stack([cube[b] for b in bands], axis=-1).astype(np.float32)
    if white is not None:
        rgb /= np.asarray([white[b] for b in bands], dtype=np.float32)
    rgb = np.clip(rgb, 0.0, None)
    top = float(np.percentile(rgb, percentile)) or 1.0
    return (np.clip(rgb / top, 0.0, 1.0) ** (1.0 / gamma) * 255.0 + 0.5).astype(np.uint8)


def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType
        return ImageFont.load_default()


def label_image(labels: np.ndarray, class_names: Sequence[str], legend: bool = True) -> Image.Image:
    """The label map in the fixed palette, with a legend strip on the right."""
    colours = [colour_of(n) for n in class_names] + [(0, 0, 0)] * (256 - len(class_names))
    lut = np.array(colours, dtype=np.uint8)
    img = Image.fromarray(lut[labels])
    if not legend:
        return img
    h = img.height
    size = max(11, h // 40)
    font = _font(size)
    row = int(size * 1.6)
    width = int(size * 14)
    out = Image.new("RGB", (img.width + width, max(h, row * (len(class_names) + 1))), (32, 32, 32))
    out.paste(img, (0, 0))
    draw = ImageDraw.Draw(out)
    for i, name in enumerate(class_names):
        y = row // 2 + i * row
        x = img.width + size
        draw.rectangle((x, y, x + size, y + size), fill=colour_of(name), outline=(128, 128, 128))
        draw.text((x + int(size * 1.5), y - size // 8), f"{i} {name}", fill=(230, 230, 230), font=font)
    return out


def label_sample(labels: np.ndarray, n: int) -> np.ndarray:
    """Labels at the centre of each n × n cell (the super-pixel grid)."""
    return labels[n // 2 :: n, n // 2 :: n]


def panel(images: Sequence[Image.Image], caption: str | None = None, width: int | None = None) -> Image.Image:
    """Images side by side (same height), optionally downscaled to ``width`` and captioned."""
    h = max(im.height for im in images)
    row = Image.new("RGB", (sum(im.width for im in images), h), (32, 32, 32))
    x = 0
    for im in images:
        row.paste(im.convert("RGB"), (x, 0))
        x += im.width
    if width and row.width > width:
        row = row.resize((width, round(row.height * width / row.width)), Image.Resampling.LANCZOS)
    if caption:
        size = max(11, row.height // 32)
        out = Image.new("RGB", (row.width, row.height + int(size * 1.8)), (32, 32, 32))
        out.paste(row, (0, int(size * 1.8)))
        ImageDraw.Draw(out).text((size // 2, size // 3), caption, fill=(230, 230, 230), font=_font(size))
        row = out
    return row


def write_snapshot(
    out_dir: str | Path, stem: str, mosaic: np.ndarray, dark: np.ndarray | None, labels: np.ndarray,
    class_names: Sequence[str], layout: Sequence[Sequence[int]], bands_nm: Sequence[float],
    white: Sequence[float] | None = None, caption: str | None = None, panel_width: int | None = None,
) -> dict[str, Path]:
    """Write ``<stem>_rgb.png``, ``<stem>_labels.png`` and, with ``panel_width``, ``<stem>_panel.png``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    img = mosaic.astype(np.float32)
    if dark is not None:
        img = np.clip(img - dark.astype(np.float32), 0.0, None)
    n = len(layout)
    cube = superpixel(img, layout, len(bands_nm))
    rgb = Image.fromarray(false_colour(cube, rgb_bands(bands_nm), white))
    lab = label_image(label_sample(labels, n), class_names)
    paths = {"rgb": out / f"{stem}_rgb.png", "labels": out / f"{stem}_labels.png"}
    rgb.save(paths["rgb"], optimize=True)
    lab.save(paths["labels"], optimize=True)
    if panel_width:
        paths["panel"] = out / f"{stem}_panel.png"
        panel([rgb, lab], caption, panel_width).save(paths["panel"], optimize=True)
    return paths
