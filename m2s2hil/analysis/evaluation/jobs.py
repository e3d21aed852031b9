"""Finding what to evaluate: one pixel-free ``FrameJob`` per image of a session, a data
root full of sessions, or an exported dataset in the published layout
(``HIL/<Satellite>/b<N>/e<N>/<light>_<k>.png``).

A job holds paths (with the journal's sha256 where there is one) and metadata only, so it
pickles cheaply to Dask workers; ``loading`` turns it into pixels.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from m2s2hil.catalog import load_catalog
from m2s2hil.config import CameraModel
from m2s2hil.errors import UsageError
from m2s2hil.plan import bracket_base_id
from m2s2hil.store.catalogue import default_data_root, list_sessions
from m2s2hil.store.importer import find_hil_root, scan_published_layout
from m2s2hil.store.layout import JOURNAL
from m2s2hil.store.session import SessionStore
from m2s2hil.store.zarr_export import zarr_frames

TRUTH_ROLE = "truth_labels"  # the ``extra`` role the engine stores the simulator's label map under
PROJECTED_ROLE = "projected_labels"  # the twin's projected labels of a HIL frame (twin.labels)


class EvaluationError(UsageError):
    """A target that cannot be evaluated (nothing found, unreadable, wrong kind)."""


@dataclass(frozen=True)
class FileRef:
    path: str
    sha256: str | None = None


@dataclass(frozen=True)
class BracketFrame:
    """One extra exposure of a job's pose (``Sweep.bracket``): its files and exposure × gain."""

    event_id: str
    cube: FileRef | None
    raw: FileRef | None
    dark: FileRef | None
    exposure: float | None  # exposure_s × gain as taken


@dataclass(frozen=True)
class FrameJob:
    """One image to evaluate: where its data is and what it shows. Picklable; pixel-free but for
    ``pose_ref``, attached only when ``spectral-pose`` is evaluated."""

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
    projected: FileRef | None = None  # the twin's projected labels (HIL columns of Table 2)
    # (segmenter name, its SweepModel or why none could be fitted) for each sweep segmenter
    # (evaluation.sweeps): a few kB of mixture, never pixels
    sweep: tuple[tuple[str, Any], ...] = ()
    exposure: float | None = None  # exposure_s × gain as the frame was taken (sessions only)
    # the factor that brings this image to its sweep's first exposure, for the sweep segmenters
    # (evaluation.sweeps; 1 when the sweep shares one exposure, as the plan's fixed exposures do)
    sweep_scale: float = 1.0
    # the pose's extra exposures (a bracketed sweep): loading merges them into this image
    bracket: tuple[BracketFrame, ...] = ()
    # ``spectral-pose``'s reference (evaluation.poses): the pose's diffuse frame's labels and
    # log-energy image (``segmenters.pose.PoseReference``, one small map each), why there is none as
    # a string, or None when no segmenter asks for one
    pose_ref: Any = None


def _camera_json(model: CameraModel) -> dict[str, Any]:
    return model.model_dump(mode="json")


def session_jobs(store: SessionStore, *, brackets: bool = True) -> list[FrameJob]:
    """One job per image of an open ``SessionStore``: per committed frame, but a bracket's extra
    exposures go with their pose's own frame (``FrameJob.bracket``) instead of making images of
    their own (``brackets=False``: every frame its own job, as the session report shows them).
    An extra exposure whose pose's own frame is missing is left out: it is not the pose's image."""
    cat = load_catalog()
    n_classes = len(cat.build(store.sweep.satellite, store.sweep.build).materials) + 1
    camera = _camera_json(store.rig.camera.model)
    darks = {d.dark_id: d for d in store.darks()}
    base = Path(store.path)

    def ref(rec: Any) -> FileRef:
        return FileRef(str(base / rec.path), rec.sha256)

    own_frames, members = [], {}
    for fr in store.frames():
        base_id = bracket_base_id(fr.event_id) if brackets else fr.event_id
        if base_id == fr.event_id:
            own_frames.append(fr)
            continue
        dark = darks.get(fr.dark_id) if fr.dark_id else None
        members.setdefault(base_id, []).append(BracketFrame(
            fr.event_id, ref(fr.files["cube"]) if "cube" in fr.files else None,
            ref(fr.files["raw"]) if "raw" in fr.files else None,
            ref(dark.files["master"]) if dark is not None else None,
            _exposure(fr.meta, fr.meta.get("event", {}))))
    jobs = []
    for fr in own_frames:
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
                projected=ref(files[PROJECTED_ROLE]) if PROJECTED_ROLE in files else None,
                exposure=_exposure(fr.meta, ev),
                bracket=tuple(members.get(fr.event_id, ())),
            )
        )
    return jobs


def _exposure(meta: Mapping[str, Any], event: Mapping[str, Any]) -> float | None:
    """exposure_s × gain as the frame records them (the plan's values when it does not); None when
    either is missing or not a positive number (an auto-exposed frame from an older session)."""
    try:
        seconds = float(meta.get("exposure_s", event.get("exposure_s")))
        value = seconds * float(meta.get("gain", event.get("gain", 1.0)))
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) and value > 0 else None


def dataset_jobs(path: str | Path) -> list[FrameJob]:
    """One job per image of an exported folder in the published layout (no ground truth).

    The lossless ``HIL16`` mosaic is used when the export wrote one, else the 8-bit ``HIL``
    PNG; cubes are super-pixel hypercubes of the default TOUCAN layout, without darks.
    """
    root = Path(path)
    hil = find_hil_root(root)
    cat = load_catalog()
    jobs = []
    for it in scan_published_layout(hil):
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
    p = Path(target)
    if (p / JOURNAL).is_file():
        with SessionStore.open_path(p) as store:
            return session_jobs(store), [f"session {store.session_id}"]
    if (p / "zarr.json").is_file():  # a zarr export (m2s2hil.store.zarr_export)
        refs = ("raw", "dark", "labels")
        jobs = [FrameJob(**{**f, **{k: FileRef(f[k]) if f[k] else None for k in refs}})
                for f in zarr_frames(p)]
        return jobs, [f"zarr export {p} ({len(jobs)} images)"]
    if p.is_dir() and ((p / "HIL").is_dir() or p.name == "HIL"):
        jobs = dataset_jobs(p)
        return jobs, [f"exported dataset {p} ({len(jobs)} images)"]
    if p.is_dir():
        sessions = [s for s in list_sessions(p) if s.state not in ("corrupt", "damaged")]
        if sessions:
            jobs, desc = [], []
            for s in sorted(sessions, key=lambda s: s.session_id):
                with SessionStore.open(p, s.session_id) as store:
                    if store.kind == "synthetic":  # no raws: evaluation.synthetic scores it
                        continue
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

