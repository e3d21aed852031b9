"""Evaluating segmenters over sessions and exported datasets (the paper's section 3).

Pipeline: ``collect_jobs(target)`` turns a session, a data root full of sessions, or an
exported dataset (``HIL/<Satellite>/b<N>/e<N>/<light>_<k>.png``) into one ``FrameJob``
per image (paths and metadata only, no pixels); ``evaluate_jobs`` runs ``evaluate_job``
on each, on Dask (``m2s2hil.analysis.parallel``); ``write_evaluation`` writes the
Table-2-shaped report (``table2``), the per-image CSV, the charts (``charts``) and a
``summary.json``.

Per image (``evaluate_job``):

- cube: the stored cube (sha256 checked against the journal), or the raw mosaic run
  through ``processing.FrameProcessor`` (the session's dark and method, or ``reprocess=``);
  exported datasets are processed from their PNG mosaic (``HIL16`` when present), without
  dark subtraction;
- ground truth: the simulator's label map the engine stored with the frame
  (``extra`` role ``truth_labels``, sensor resolution), reduced to the cube's grid by the
  majority label of each n×n cell (``labels_to_cube``); images without it get mTC only;
- every segmenter of ``EvalOptions.segmenters`` runs once (timed: ``time_s`` is the
  segmentation only), its clusters are matched to classes (oracle Hungarian matching,
  ``score_clusters``, label set = ground-truth classes, 0/0 = 0) and scored (macro P, R,
  Dice, micro-IoU);
- mTC (K = 8 seeded shifts, ``analysis.mtc``) of the multispectral segmenter (or every
  segmenter, ``mtc="all"``). ``mtc_mode="labels"`` (default): the segmenter's full label
  map, each shifted prediction aligned to the base one (Hungarian, 0 ↔ 0).
  ``mtc_mode="binary"``: the paper's HIL setting, bands 5, 9, 10 segmented one by one and
  fused as foreground/background (RGB segmenters: their prediction's foreground). With a
  pixel-wise segmenter (``spectral``) binary mTC is exactly 1.0 (a shift is undone
  exactly), which is why it is not the default.

Segmenter names: every registered name (``create_segmenter``) plus ``spectral-smooth`` /
``rgb-smooth`` (``smooth=True``: SLIC superpixel majority vote). Table 2 pairs the
multispectral segmenter with its RGB counterpart (``RGB_COUNTERPART``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import platform
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np

from m2s2hil.analysis.errors import AnalysisInputError
from m2s2hil.analysis.metrics import score_clusters
from m2s2hil.analysis.mtc import PAPER_BANDS, band_fused_predictor, mtc
from m2s2hil.analysis.segment import Segmenter, create_segmenter
from m2s2hil.catalog import load_catalog
from m2s2hil.errors import UsageError
from m2s2hil.frame_files import decode_tiff

log = logging.getLogger(__name__)

MtcFor = Literal["multi", "all", "none"]
MtcMode = Literal["labels", "binary"]
RGB_COUNTERPART = {"spectral": "rgb", "spectral-smooth": "rgb-smooth", "sam": "sam-rgb"}
TRUTH_ROLE = "truth_labels"
LIGHTING_ORDER = ("directional", "weak", "strong")


class EvaluationError(UsageError):
    """A target that cannot be evaluated (nothing found, unreadable, wrong kind)."""


# ----------------------------------------------------------------------------- jobs and options
@dataclass(frozen=True)
class FileRef:
    path: str
    sha256: str | None = None


@dataclass(frozen=True)
class FrameJob:
    """One image to evaluate: where its data is and what it shows. Picklable, pixel-free."""

    image_id: str
    source: str  # session id, or the dataset folder
    satellite: str  # catalog key
    build: str
    n_classes: int  # materials + background, as the paper counts
    elevation: str
    lighting: str
    azimuth_deg: float | None
    camera: dict[str, Any]  # CameraModel as JSON
    method: str  # demosaicing method used when the cube comes from the raw
    cube: FileRef | None = None
    raw: FileRef | None = None
    raw_kind: Literal["tiff", "png"] = "tiff"
    dark: FileRef | None = None
    labels: FileRef | None = None
    preview: FileRef | None = None


@dataclass(frozen=True)
class EvalOptions:
    """What ``evaluate_job`` computes for each image."""

    multi: str = "spectral"
    rgb: str | None = None  # default: RGB_COUNTERPART[multi]
    extra: tuple[str, ...] = ()  # more segmenters (speed/accuracy chart, per-image CSV)
    segmenter_options: dict[str, Any] = field(default_factory=dict)
    mtc_for: MtcFor = "multi"
    mtc_mode: MtcMode = "labels"
    reprocess: str | None = None  # demosaicing method: recompute cubes from the raw
    rho: float = 0.9

    def __post_init__(self) -> None:
        if self.mtc_for not in ("multi", "all", "none"):
            raise UsageError(f"mtc must be one of multi, all, none; got {self.mtc_for!r}")
        if self.mtc_mode not in ("labels", "binary"):
            raise UsageError(f"mtc mode must be 'labels' or 'binary', got {self.mtc_mode!r}")
        if self.multi.startswith(("rgb", "sam-rgb")):
            raise UsageError(
                f"{self.multi!r} is an RGB baseline: choose the multispectral segmenter "
                f"({', '.join(RGB_COUNTERPART)}); its RGB counterpart is evaluated with it"
            )
        if not -1.0 <= self.rho <= 1.0:
            raise UsageError(f"rho must lie in [-1, 1], got {self.rho}")

    @property
    def rgb_name(self) -> str:
        return self.rgb or RGB_COUNTERPART.get(self.multi, "rgb")

    @property
    def segmenters(self) -> tuple[str, ...]:
        names = [self.multi, self.rgb_name, *self.extra]
        return tuple(dict.fromkeys(names))


def make_segmenter(
    name: str, options: Mapping[str, Any] | None = None, *, bands_nm: Sequence[float] | None = None
) -> Segmenter:
    """A segmenter by name (see module docstring); ``bands_nm`` feeds the RGB rendering."""
    opts = dict(options or {})
    base = name
    if name.endswith("-smooth"):
        base = name[: -len("-smooth")]
        opts["smooth"] = True
    if base in ("rgb", "sam-rgb") and bands_nm is not None:
        opts.setdefault("bands_nm", tuple(float(b) for b in bands_nm))
    if base in ("sam", "sam-rgb"):
        opts = {k: v for k, v in opts.items() if k not in ("smooth",)}
    elif "checkpoint" in opts:
        opts.pop("checkpoint")
    seg = create_segmenter(base, **opts)
    if base != name:
        seg.name = name  # type: ignore[misc]
    return seg


def check_segmenters(options: EvalOptions) -> None:
    """Build every segmenter once here, so a missing model fails before any work is sent."""
    for name in options.segmenters:
        make_segmenter(name, options.segmenter_options)


# ----------------------------------------------------------------------------- pixels
def labels_to_cube(labels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Ground truth on the cube's grid: as is if the shapes agree, else the majority label
    of each n×n cell (ties: the lowest id) when the sensor is n times larger."""
    lab = np.asarray(labels)
    if lab.ndim != 2:
        raise AnalysisInputError("labels", f"expected an (H, W) label map, got shape {lab.shape}")
    if lab.shape == tuple(shape):
        return lab.astype(np.int64)
    h, w = shape
    n = lab.shape[0] // h if h else 0
    if n < 1 or lab.shape != (h * n, w * n):
        raise AnalysisInputError(
            "labels", f"label map {lab.shape} is not an integer multiple of the cube {shape}"
        )
    cells = lab.reshape(h, n, w, n).transpose(0, 2, 1, 3).reshape(h * w, n * n).astype(np.int64)
    k = int(cells.max()) + 1
    counts = np.zeros((h * w, k), dtype=np.int32)
    np.add.at(counts, (np.repeat(np.arange(h * w), n * n), cells.ravel()), 1)
    return counts.argmax(axis=1).reshape(h, w)


def _read(ref: FileRef) -> bytes:
    data = Path(ref.path).read_bytes()
    if ref.sha256 and hashlib.sha256(data).hexdigest() != ref.sha256:
        raise EvaluationError(f"{ref.path}: sha256 does not match the session journal")
    return data


# Per-thread caches: a FrameProcessor reuses its output buffers, so worker threads of a
# threaded cluster must not share one.
_CACHE = threading.local()


def _cache(name: str) -> dict[tuple, Any]:
    d = getattr(_CACHE, name, None)
    if d is None:
        d = {}
        setattr(_CACHE, name, d)
    return d


def _processor(job: FrameJob, method: str, shape: tuple[int, int] | None = None) -> Any:
    """A FrameProcessor per (method, camera, dark), cached per worker process (its buffers
    are large for the full-resolution methods)."""
    from m2s2hil.config import CameraModel
    from m2s2hil.processing.dark import MasterDark
    from m2s2hil.processing.pipeline import FrameProcessor

    camera = dict(job.camera)
    if shape is not None:  # exported PNGs: the sensor size is the file's
        camera.update(height=int(shape[0]), width=int(shape[1]))
    key = (method, json.dumps(camera, sort_keys=True), job.dark.path if job.dark else None)
    procs = _cache("processors")
    proc = procs.get(key)
    if proc is None:
        dark = None
        if job.dark is not None:
            arr, meta = decode_tiff(_read(job.dark))
            data = np.clip(np.rint(arr), 0, 65535).astype(np.uint16)
            dark = MasterDark(
                data=data,
                created=str(meta.get("created", "")),
                camera_serial="unknown",
                n_frames=int(meta.get("n_frames", 1) or 1),
                exposure_s=float(meta.get("exposure_s", 0.0) or 0.0),
                gain=float(meta.get("gain", 1.0) or 1.0),
                temperature_c=float(meta.get("temperature_c", math.nan) or math.nan),
            )
        if len(procs) >= 4:
            procs.clear()
        proc = procs[key] = FrameProcessor(method, CameraModel.model_validate(camera), dark=dark)
    return proc


def load_cube(job: FrameJob, reprocess: str | None = None) -> np.ndarray:
    """The image's float32 cube (bands, H, W): stored, or processed from the raw."""
    from m2s2hil.frame_files import decode_png

    if job.cube is not None and reprocess is None:
        cube, _ = decode_tiff(_read(job.cube))
        return np.asarray(cube, dtype=np.float32)
    if job.raw is None:
        raise EvaluationError(f"{job.image_id}: neither a cube nor a raw mosaic to evaluate")
    data = _read(job.raw)
    if job.raw_kind == "png":
        raw = decode_png(data)
        if raw.ndim == 3:
            raw = raw[..., 0]
        raw = raw.astype(np.uint16)
        proc = _processor(job, reprocess or job.method, raw.shape)
    else:
        raw = decode_tiff(data)[0].astype(np.uint16)
        proc = _processor(job, reprocess or job.method)
    return np.array(proc.process(raw).cube, dtype=np.float32, copy=True)


def load_truth(job: FrameJob, shape: tuple[int, int]) -> np.ndarray | None:
    if job.labels is None:
        return None
    from m2s2hil.frame_files import decode_png

    data = _read(job.labels)
    arr = decode_tiff(data)[0] if job.labels.path.endswith((".tif", ".tiff")) else decode_png(data)
    return labels_to_cube(arr, shape)


# ----------------------------------------------------------------------------- one image
def _segmenter(name: str, options: EvalOptions, bands_nm: Sequence[float]) -> Segmenter:
    key = (name, json.dumps(options.segmenter_options, sort_keys=True, default=str), tuple(bands_nm))
    segs = _cache("segmenters")
    seg = segs.get(key)
    if seg is None:
        seg = segs[key] = make_segmenter(name, options.segmenter_options, bands_nm=bands_nm)
    return seg


def is_rgb(name: str) -> bool:
    return name.startswith(("rgb", "sam-rgb"))


def mtc_predictor(seg: Segmenter, name: str, mode: MtcMode, n_bands: int) -> tuple[Callable, bool]:
    """(predictor, align) for ``analysis.mtc`` (see the module docstring)."""
    if mode == "labels":
        return seg.segment, True
    if is_rgb(name) or n_bands < max(PAPER_BANDS):
        return (lambda c: (seg.segment(c) > 0).astype(np.int64)), False
    return band_fused_predictor(seg.segment, PAPER_BANDS, binary=True), False


def evaluate_job(job: FrameJob, options: EvalOptions) -> dict[str, Any]:
    """Scores of every segmenter on one image; errors are returned in the record, not raised."""
    rec: dict[str, Any] = {
        "image_id": job.image_id,
        "source": job.source,
        "satellite": job.satellite,
        "build": job.build,
        "classes": job.n_classes,
        "elevation": job.elevation,
        "lighting": job.lighting,
        "azimuth_deg": job.azimuth_deg,
        "has_truth": False,
        "error": None,
        "results": {},
    }
    try:
        t0 = time.perf_counter()
        cube = load_cube(job, options.reprocess)
        gt = load_truth(job, cube.shape[1:])
        rec["load_s"] = time.perf_counter() - t0
        rec["has_truth"] = gt is not None
        rec["cube_shape"] = list(cube.shape)
        bands_nm = job.camera.get("bands_nm") or ()
        for name in options.segmenters:
            seg = _segmenter(name, options, bands_nm)
            t1 = time.perf_counter()
            pred = seg.segment(cube)
            res: dict[str, Any] = {
                "time_s": time.perf_counter() - t1,
                "n_segments": len(np.unique(pred[pred > 0])),
            }
            if gt is not None:
                s, _ = score_clusters(gt, pred)
                res.update(
                    precision=s.macro_precision,
                    recall=s.macro_recall,
                    dice=s.macro_dice,
                    micro_iou=s.micro_iou,
                )
            if options.mtc_for == "all" or (options.mtc_for == "multi" and name == options.multi):
                predict, align = mtc_predictor(seg, name, options.mtc_mode, cube.shape[0])
                t2 = time.perf_counter()
                r = mtc(predict, cube, align=align)
                res.update(mtc=r.score, mtc_time_s=time.perf_counter() - t2)
            rec["results"][name] = res
    except Exception as exc:  # one bad image must not end a 16,000-image run; it is reported
        log.warning("evaluation of %s failed: %s", job.image_id, exc)
        rec["error"] = f"{type(exc).__name__}: {exc}"
    return rec


# ----------------------------------------------------------------------------- collecting jobs
def _camera_json(model: Any) -> dict[str, Any]:
    return model.model_dump(mode="json")


def session_jobs(store: Any) -> list[FrameJob]:
    """One job per committed frame of an open ``SessionStore``."""
    cat = load_catalog()
    n_classes = len(cat.build(store.sweep.satellite, store.sweep.build).materials) + 1
    camera = _camera_json(store.rig.camera.model)
    darks = {d.dark_id: d for d in store.darks()}
    base = Path(store.path)

    def ref(rec: Any) -> FileRef:
        return FileRef(str(base / rec.path), rec.sha256)

    jobs = []
    for fr in store.frames():
        ev = fr.meta.get("event", {})
        files = fr.files
        dark = darks.get(fr.dark_id) if fr.dark_id else None
        labels = ref(files[TRUTH_ROLE]) if TRUTH_ROLE in files else None
        if labels is None and isinstance(fr.meta.get("truth_labels"), Mapping):  # engine without extra=
            t = fr.meta["truth_labels"]
            labels = FileRef(str(base / t["path"]), t.get("sha256"))
        jobs.append(
            FrameJob(
                image_id=f"{store.session_id}/{fr.event_id}",
                source=store.session_id,
                satellite=store.sweep.satellite,
                build=store.sweep.build,
                n_classes=n_classes,
                elevation=str(ev.get("elevation", "")),
                lighting=str(ev.get("lighting", "")),
                azimuth_deg=ev.get("nominal_azimuth_deg"),
                camera=camera,
                method=str(fr.meta.get("processing_method") or store.sweep.processing),
                cube=ref(files["cube"]) if "cube" in files else None,
                raw=ref(files["raw"]) if "raw" in files else None,
                dark=ref(dark.files["master"]) if dark is not None else None,
                labels=labels,
                preview=ref(files["preview"]) if "preview" in files else None,
            )
        )
    return jobs


def dataset_jobs(path: str | Path) -> list[FrameJob]:
    """One job per image of an exported folder in the published layout (no ground truth).

    The lossless ``HIL16`` mosaic is used when the export wrote one, else the 8-bit ``HIL``
    PNG; cubes are super-pixel hypercubes of the default TOUCAN layout, without darks.
    """
    from m2s2hil.config import CameraModel
    from m2s2hil.importer import _find_hil, _scan

    root = Path(path)
    hil = _find_hil(root)
    cat = load_catalog()
    jobs = []
    for it in _scan(hil):
        rel = Path(it.rel).relative_to("HIL")
        p16 = hil.parent / "HIL16" / rel
        use16 = p16.is_file()
        model = CameraModel(bit_depth=10 if use16 else 8)
        step = 10.0
        jobs.append(
            FrameJob(
                image_id=it.rel,
                source=str(root),
                satellite=it.satellite,
                build=it.build,
                n_classes=len(cat.build(it.satellite, it.build).materials) + 1,
                elevation=it.elevation,
                lighting=it.lighting,
                azimuth_deg=(it.k % 36) * step,
                camera=_camera_json(model),
                method="superpixel",
                raw=FileRef(str(p16 if use16 else it.path)),
                raw_kind="png",
            )
        )
    return jobs


def collect_jobs(target: str | Path, root: str | Path | None = None) -> tuple[list[FrameJob], list[str]]:
    """Jobs and a description of each source for: a session folder, a session id under
    ``root``, a data root holding sessions, or an exported dataset folder."""
    from m2s2hil.store import JOURNAL, SessionStore, default_data_root, list_sessions

    p = Path(target)
    if (p / JOURNAL).is_file():
        with SessionStore.open_path(p) as store:
            return session_jobs(store), [f"session {store.session_id}"]
    if p.is_dir() and ((p / "HIL").is_dir() or p.name == "HIL"):
        jobs = dataset_jobs(p)
        return jobs, [f"exported dataset {p} ({len(jobs)} images)"]
    if p.is_dir():
        sessions = [s for s in list_sessions(p) if s.state != "corrupt"]
        if sessions:
            jobs, desc = [], []
            for s in sorted(sessions, key=lambda s: s.session_id):
                with SessionStore.open(p, s.session_id) as store:
                    jobs += session_jobs(store)
                desc.append(f"session {s.session_id}")
            return jobs, desc
    base = Path(root) if root is not None else default_data_root()
    if (base / str(target) / JOURNAL).is_file():
        with SessionStore.open(base, str(target)) as store:
            return session_jobs(store), [f"session {store.session_id}"]
    raise EvaluationError(
        f"{target}: not a session folder, a session id under {base}, a data root with sessions, "
        "or an exported dataset (a folder with HIL/)"
    )


# ----------------------------------------------------------------------------- running
@dataclass
class EvaluationResult:
    records: list[dict[str, Any]]
    options: EvalOptions
    sources: list[str]
    elapsed_s: float
    compute: dict[str, Any]

    @property
    def has_truth(self) -> bool:
        return any(r["has_truth"] for r in self.records)

    @property
    def errors(self) -> list[dict[str, Any]]:
        return [r for r in self.records if r.get("error")]


def evaluate_jobs(
    jobs: Sequence[FrameJob],
    options: EvalOptions,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    processes: bool = True,
    sources: Sequence[str] = (),
    progress: Callable[[int, int], None] | None = None,
) -> EvaluationResult:
    """Run ``evaluate_job`` over ``jobs`` on Dask (``workers=0``: in this process)."""
    from m2s2hil.analysis.parallel import dask_client, describe, map_ordered

    if not jobs:
        raise EvaluationError("nothing to evaluate: no images found")
    check_segmenters(options)
    total = len(jobs)

    def on_result(done: int, _rec: Any) -> None:
        if progress is not None:
            progress(done, total)

    t0 = time.perf_counter()
    if workers == 0 and not scheduler:
        records = map_ordered(evaluate_job, list(jobs), client=None, on_result=on_result, options=options)
        compute = describe(None)
    else:
        with dask_client(scheduler, workers=workers, processes=processes) as client:
            compute = describe(client)
            records = map_ordered(
                evaluate_job, list(jobs), client=client, on_result=on_result, options=options
            )
    return EvaluationResult(records, options, list(sources), time.perf_counter() - t0, compute)


# ----------------------------------------------------------------------------- aggregates
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
                "error",
            )
        }
        if not r.get("results"):
            rows.append({**keys, "segmenter": ""})
        for name, res in r.get("results", {}).items():
            rows.append({**keys, "segmenter": name, **res})
    return rows


def speed_accuracy(records: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Per segmenter: mean/SD time per image and macro Dice over the images with ground truth."""
    by: dict[str, dict[str, list[float]]] = {}
    for r in records:
        for name, res in r.get("results", {}).items():
            d = by.setdefault(name, {"time": [], "dice": [], "mtc": []})
            d["time"].append(float(res["time_s"]))
            if "dice" in res and res["dice"] is not None and math.isfinite(res["dice"]):
                d["dice"].append(float(res["dice"]))
            if "mtc" in res:
                d["mtc"].append(float(res["mtc"]))
    out = []
    for name, d in by.items():
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
    import os

    return (
        f"{platform.machine()} {os.cpu_count()} cores, {platform.system()} {platform.release()}, "
        f"Python {platform.python_version()}"
    )


def write_evaluation(result: EvaluationResult, out: str | Path) -> dict[str, Path]:
    """Write table2.csv/.md, per_image.csv, significance.md, the charts and summary.json into ``out``."""
    from m2s2hil.analysis import charts, table2
    from m2s2hil.atomic import write_text_atomic

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
            table2.significance_markdown(result.records, rows, multi=opts.multi, rgb=opts.rgb_name),
        )
        written["significance.md"] = out / "significance.md"
    speed = speed_accuracy(result.records)
    written.update(charts.write_evaluation_charts(out, rows, speed, has_truth=result.has_truth))
    summary = {
        "written": datetime.now(UTC).isoformat(timespec="seconds"),
        "sources": result.sources,
        "images": len(result.records),
        "images_with_truth": sum(r["has_truth"] for r in result.records),
        "errors": [{"image_id": r["image_id"], "error": r["error"]} for r in result.errors],
        "options": {**asdict(opts), "segmenters": list(opts.segmenters), "rgb": opts.rgb_name},
        "elapsed_s": result.elapsed_s,
        "compute": result.compute,
        "machine": machine(),
        "speed_accuracy": speed,
        "notes": notes,
    }
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2, sort_keys=True, default=str) + "\n")
    written["summary.json"] = out / "summary.json"
    return written


# ----------------------------------------------------------------------------- simulated sessions
def simulate_session(
    root: str | Path,
    *,
    satellite: str,
    build: str,
    lighting: Sequence[str] = ("weak",),
    tilts: Sequence[str] = ("E0",),
    azimuth_step_deg: float = 90.0,
    exposure: Mapping[str, float] | None = None,
    size: int = 256,
    seed: int = 0,
    qc: Any = True,
    session_id: str | None = None,
    dark_frames: int = 2,
) -> Path:
    """Capture a session on the simulated rig with the real engine (truth labels stored with
    every frame); ``size`` is the sensor width = height; ``qc``: True (default hook), a
    hook, or None. Returns the session folder."""
    from m2s2hil.analysis.qc import capture_qc_hook
    from m2s2hil.config import default_rig, parse_rig
    from m2s2hil.engine import Engine
    from m2s2hil.plan import Sweep
    from m2s2hil.simrig import open_simulated_rig
    from m2s2hil.store import SessionStore

    data = default_rig().model_dump(mode="json")
    data["camera"]["model"].update(width=int(size), height=int(size))
    cfg = parse_rig(data, f"simulated rig ({size}x{size})")
    sweep_data: dict[str, Any] = {
        "satellite": satellite,
        "build": build,
        "lighting": list(lighting),
        "tilts": list(tilts),
        "azimuth_step_deg": azimuth_step_deg,
        "dark": {"frames": dark_frames},
    }
    if exposure:
        sweep_data["exposure"] = dict(exposure)
    sweep = Sweep.model_validate(sweep_data)
    hook = capture_qc_hook() if qc is True else (qc or None)
    rig = open_simulated_rig(cfg, seed=seed)
    try:
        store = SessionStore.create(root, sweep, cfg, session_id=session_id, clock=rig.clock)
        with store:
            Engine(rig, store, sweep, qc=hook).run()
            return Path(store.path)
    finally:
        rig.close()


# The failure study (docs/evaluation.md): one simulated session per scenario.
SCENARIOS: dict[str, dict[str, Any]] = {
    "diffuse": {"satellite": "voyager", "build": "B2", "lighting": ("weak", "strong")},
    "directional": {"satellite": "voyager", "build": "B2", "lighting": ("directional",)},
    "11 classes (ISS B3)": {"satellite": "iss", "build": "B3", "lighting": ("weak",)},
    "low light (0.2 ms)": {
        "satellite": "voyager",
        "build": "B2",
        "lighting": ("weak",),
        "exposure": {"weak": 0.0002},
    },
    "saturation (50 ms)": {
        "satellite": "voyager",
        "build": "B2",
        "lighting": ("strong",),
        "exposure": {"strong": 0.05},
    },
}


def stability_study(
    root: str | Path,
    out: str | Path,
    *,
    size: int = 512,
    azimuth_step_deg: float = 45.0,
    segmenters: Sequence[str] = ("spectral", "rgb", "spectral-smooth"),
    scenarios: Mapping[str, Mapping[str, Any]] | None = None,
    scheduler: str | None = None,
    workers: int | None = None,
    processes: bool = True,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """Simulate each scenario, evaluate every segmenter with mTC, write stability.csv/.md/.png to ``out``."""
    from m2s2hil.analysis import charts, table2
    from m2s2hil.analysis.qc import qc_of_meta
    from m2s2hil.atomic import write_text_atomic
    from m2s2hil.store import SessionStore

    chosen = dict(scenarios or SCENARIOS)
    root = Path(root)
    jobs: list[FrameJob] = []
    scenario_of: dict[str, str] = {}
    qc: dict[str, list[tuple[float | None, list[str]]]] = {}
    for i, (name, spec) in enumerate(chosen.items()):
        sid = f"stability-{i}"
        folder = simulate_session(
            root, size=size, azimuth_step_deg=azimuth_step_deg, seed=seed, session_id=sid, **dict(spec)
        )
        with SessionStore.open_path(folder) as store:
            jobs += session_jobs(store)
            qc[name] = [qc_of_meta(fr.meta) for fr in store.frames()]
        scenario_of[sid] = name
    multi = next((s for s in segmenters if not is_rgb(s)), "spectral")
    opts = EvalOptions(multi=multi, extra=tuple(s for s in segmenters if s != multi), mtc_for="all")
    result = evaluate_jobs(
        jobs,
        opts,
        scheduler=scheduler,
        workers=workers,
        processes=processes,
        sources=[f"scenario {n}" for n in chosen],
    )
    rows = []
    for name in chosen:
        recs = [r for r in result.records if scenario_of.get(r["source"]) == name and not r.get("error")]
        scores = [s for s, _ in qc[name] if s is not None]
        for seg in opts.segmenters:
            res = [r["results"][seg] for r in recs if seg in r["results"]]

            def mean(key: str, res: list[dict[str, Any]] = res) -> float:
                vals = [
                    float(x[key]) for x in res if key in x and x[key] is not None and math.isfinite(x[key])
                ]
                return float(np.mean(vals)) if vals else math.nan

            rows.append(
                {
                    "scenario": name,
                    "segmenter": seg,
                    "images": len(res),
                    "precision": mean("precision"),
                    "recall": mean("recall"),
                    "dice": mean("dice"),
                    "mtc": mean("mtc"),
                    "time_s": mean("time_s"),
                    "qc_mean": float(np.mean(scores)) if scores else math.nan,
                    "qc_flagged": sum(bool(f) for _, f in qc[name]),
                }
            )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "stability.csv", table2.rows_csv(rows))
    write_text_atomic(out / "stability.md", stability_markdown(rows))
    charts.stability_chart(rows, out / "stability.png")
    charts.speed_accuracy_chart(
        speed_accuracy(result.records),
        out / "speed_accuracy.png",
        title="Speed against accuracy (all scenarios)",
    )
    write_text_atomic(
        out / "stability_records.json",
        json.dumps(
            {
                "records": result.records,
                "compute": result.compute,
                "elapsed_s": result.elapsed_s,
                "machine": machine(),
                "size": size,
            },
            indent=1,
            default=str,
        )
        + "\n",
    )
    return rows


def stability_markdown(rows: Sequence[Mapping[str, Any]]) -> str:
    def f(v: Any) -> str:
        return "–" if not isinstance(v, (int, float)) or not math.isfinite(v) else f"{v:.3f}"

    lines = [
        "| Scenario | Segmenter | Images | Macro P | Macro R | Dice | mTC | s/image | QC mean | QC flagged |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scenario']} | {r['segmenter']} | {r['images']} | {f(r['precision'])} | "
            f"{f(r['recall'])} | {f(r['dice'])} | {f(r['mtc'])} | {f(r['time_s'])} | {f(r['qc_mean'])} | "
            f"{r['qc_flagged']} |"
        )
    return "\n".join(lines) + "\n"


__all__ = [
    "RGB_COUNTERPART",
    "EvalOptions",
    "EvaluationError",
    "EvaluationResult",
    "FileRef",
    "FrameJob",
    "collect_jobs",
    "dataset_jobs",
    "evaluate_job",
    "evaluate_jobs",
    "labels_to_cube",
    "load_cube",
    "make_segmenter",
    "per_image_rows",
    "session_jobs",
    "simulate_session",
    "speed_accuracy",
    "stability_study",
    "write_evaluation",
]
