"""Summaries of per-image evaluation records (``evaluate.evaluate_job``): the rows of
per_image.csv, speed against accuracy per segmenter, and the machine they ran on."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from m2s2hil.hostinfo import describe_machine


def per_image_rows(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per (image, segmenter) for per_image.csv."""
    rows = []
    for r in records:
        keys = {
            k: r.get(k)
            for k in (
                "image_id",
                "source",
                "satellite",
                "build",
                "classes",
                "elevation",
                "lighting",
                "azimuth_deg",
                "has_truth",
                "clipped_fraction",
                "error",
                "mask_error",
                "bracket_frames",
                "bracket_error",
            )
        }
        if not r.get("results"):
            rows.append({**keys, "segmenter": ""})
        for name, res in r.get("results", {}).items():
            values = {k: v for k, v in res.items() if k != "errors"}
            failed = "; ".join(f"{step}: {err}" for step, err in res.get("errors", {}).items())
            rows.append({**keys, "segmenter": name, **values, "failed": failed})
    return rows


def speed_accuracy(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per segmenter: mean/SD time per image and macro Dice over the images with ground truth."""
    by: dict[str, dict[str, list[float]]] = {}
    for r in records:
        for name, res in r.get("results", {}).items():
            d = by.setdefault(name, {"time": [], "dice": [], "mtc": []})
            if "time_s" not in res:  # the segmenter failed on this image (res["errors"])
                continue
            d["time"].append(float(res["time_s"]))
            if "dice" in res and res["dice"] is not None and math.isfinite(res["dice"]):
                d["dice"].append(float(res["dice"]))
            if "mtc" in res:
                d["mtc"].append(float(res["mtc"]))
    out = []
    for name, d in by.items():
        if not d["time"]:
            continue
        t, dice, m = np.array(d["time"]), np.array(d["dice"]), np.array(d["mtc"])
        out.append(
            {
                "segmenter": name,
                "images": int(t.size),
                "time_mean_s": float(t.mean()),
                "time_sd_s": float(t.std(ddof=1)) if t.size > 1 else 0.0,
                "dice_mean": float(dice.mean()) if dice.size else math.nan,
                "dice_sd": float(dice.std(ddof=1)) if dice.size > 1 else math.nan,
                "mtc_mean": float(m.mean()) if m.size else math.nan,
                "scored_images": int(dice.size),
            }
        )
    return out


def machine() -> str:
    """The machine line recorded with timings (summary.json, benchmark notes)."""
    return describe_machine()
