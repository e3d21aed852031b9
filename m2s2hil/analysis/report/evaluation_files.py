"""The evaluation's report folder: Table 2 (CSV, Markdown), the per-image and per-lighting CSVs,
the significance notes, the charts and ``summary.json`` (docs/evaluation.md lists each file).

``summary.json`` is strict JSON: non-finite numbers become ``null`` (``json_safe``).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from m2s2hil.analysis.evaluation import table2
from m2s2hil.analysis.evaluation.aggregates import machine, per_image_rows, speed_accuracy
from m2s2hil.analysis.evaluation.evaluate import EvaluationResult
from m2s2hil.analysis.report import charts
from m2s2hil.atomic import write_text_atomic


def json_safe(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None, so ``json.dumps(allow_nan=False)``
    writes valid JSON (``null``, never ``NaN``)."""
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    return value


def write_evaluation(result: EvaluationResult, out: str | Path) -> dict[str, Path]:
    """Write table2.csv/.md, per_image.csv, significance.md, the charts and summary.json into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    opts = result.options
    rows = table2.build_rows(result.records, multi=opts.multi, rgb=opts.rgb_name, rho=opts.rho)
    written: dict[str, Path] = {}
    notes = table2.notes(result, rows)
    write_text_atomic(out / "table2.csv", table2.to_csv(rows))
    write_text_atomic(out / "table2.md", table2.to_markdown(rows, notes=notes))
    written["table2.csv"], written["table2.md"] = out / "table2.csv", out / "table2.md"
    write_text_atomic(out / "per_image.csv", table2.rows_csv(per_image_rows(result.records)))
    written["per_image.csv"] = out / "per_image.csv"
    by_light = table2.by_lighting(result.records, segmenters=opts.segmenters)
    write_text_atomic(out / "by_lighting.csv", table2.rows_csv(by_light))
    written["by_lighting.csv"] = out / "by_lighting.csv"
    if result.has_truth:
        write_text_atomic(
            out / "significance.md",
            table2.significance_markdown(
                result.records, rows, multi=opts.multi, rgb=opts.rgb_name, rho=opts.rho
            ),
        )
        written["significance.md"] = out / "significance.md"
    speed = speed_accuracy(result.records)
    written.update(
        charts.write_evaluation_charts(
            out, rows, speed, has_truth=result.has_truth, rho=opts.rho,
            mtc_mode=opts.mtc_mode if opts.mtc_for != "none" else None, multi=opts.multi,
        )
    )
    summary = {
        "written": datetime.now(UTC).isoformat(timespec="seconds"),
        "sources": result.sources,
        "images": len(result.records),
        "images_with_truth": sum(r["has_truth"] for r in result.records),
        "errors": [{"image_id": r["image_id"], "error": r["error"]} for r in result.errors],
        "metric_errors": result.metric_errors,
        "bands": result.bands,
        "options": {**asdict(opts), "segmenters": list(opts.segmenters), "rgb": opts.rgb_name},
        "elapsed_s": result.elapsed_s,
        "compute": result.compute,
        "machine": machine(),
        "speed_accuracy": speed,
        "notes": notes,
    }
    text = json.dumps(json_safe(summary), indent=2, sort_keys=True, default=str, allow_nan=False)
    write_text_atomic(out / "summary.json", text + "\n")
    written["summary.json"] = out / "summary.json"
    return written
