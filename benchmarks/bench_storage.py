"""Session storage: codecs for raw frames and darks, cubes computed on read, and a full build in
today's (compressed) format against the legacy one, side by side in one run.

    .venv/bin/python benchmarks/bench_storage.py [--only codecs,cube,build] [--repeat 3]

codecs  simulated 2048² frames of every lighting (weak, strong, directional; two satellites,
        two azimuths each, at the plan's exposures) through tifffile with each candidate
        compression: mean size, ratio, write and read time (one thread, median), and whether
        Pillow and OpenCV read the file back exactly. Also the master dark: float32
        uncompressed (legacy) against uint16 deflate.
cube    reading a frame's cube: decoding a stored float32 cube (legacy) against computing it
        from raw + dark (``SessionStore.read_cube``).
build   the full build (voyager B3, 324 frames, 3 darks, 2048², the engine's defaults) with
        ``[storage] format = "legacy"`` and ``"compressed"``: wall time, bytes per frame (every
        file of the session / frames), storage-thread time.

Each build runs in its own interpreter, the formats alternate per round, and every build starts
after ``os.sync()`` and a pause, so none inherits the previous one's heap or pending disk work.
Wall times depend on the shared machine's load; sizes are exact for these frames.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import tifffile
from PIL import Image

from m2s2hil.config import RigConfig, StorageConfig, default_rig
from m2s2hil.hostinfo import describe_machine
from m2s2hil.plan import DEFAULT_EXPOSURE_S, Sweep
from m2s2hil.store.frame_files import encode_dark, encode_raw

SETTLE_S = 5.0  # pause between builds, after os.sync(), for the disk to finish the last one's work

CODECS: list[tuple[str, dict]] = [
    ("none", {}),
    ("deflate 1, libdeflate (tifffile's own)", {"compression": "zlib", "compressionargs": {"level": 1}}),
    # what the store writes: 64-row strips deflated by ISA-L level 1 (m2s2hil.store.frame_files)
    ("deflate 1, ISA-L strips (the store's)", {"store": True}),
    ("deflate 1 + predictor", {"compression": "zlib", "compressionargs": {"level": 1}, "predictor": True}),
    ("deflate 4", {"compression": "zlib", "compressionargs": {"level": 4}}),
    ("deflate 6 + predictor", {"compression": "zlib", "compressionargs": {"level": 6}, "predictor": True}),
    ("zstd 1", {"compression": "zstd", "compressionargs": {"level": 1}}),
    ("zstd 3", {"compression": "zstd", "compressionargs": {"level": 3}}),
    ("zstd 1 + predictor", {"compression": "zstd", "compressionargs": {"level": 1}, "predictor": True}),
    ("LZW + predictor", {"compression": "lzw", "predictor": True}),
]


def sim_frames() -> tuple[dict[tuple[str, str, float], np.ndarray], list[np.ndarray]]:
    """Raw frames of every lighting, and 8 dark frames, from the simulator's frame source."""
    from m2s2hil.simulators.clock import VirtualClock

    from m2s2hil.sim_config import build_frame_source, build_world

    cfg = default_rig()
    clock = VirtualClock()
    world = build_world(cfg, clock)  # the simulated rig's own world and frame source
    pose = {"az": 0.0}
    world.attach_axis("turntable", lambda: pose["az"])
    world.attach_axis("tilt", lambda: 0.0)
    src = build_frame_source(cfg, world)
    frames = {}
    for sat, build in (("voyager", "B3"), ("hubble", "B2")):
        world.mount(sat, build)
        for light in ("weak", "strong", "directional"):
            for ch in range(8):
                world.set_lamp(ch, False)
            for ch in cfg.lamp_channels(light):
                world.set_lamp(ch, True)
            clock.advance(5.0)
            for az in (30.0, 120.0):
                pose["az"] = az
                frames[(sat, light, az)] = src.capture(DEFAULT_EXPOSURE_S[light]).copy()
    for ch in range(8):
        world.set_lamp(ch, False)
    darks = [src.capture(DEFAULT_EXPOSURE_S["weak"]).copy() for _ in range(8)]
    return frames, darks


def _time(fn, repeat: int) -> float:
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return statistics.median(out) * 1e3


def _write(buf: io.BytesIO, arr: np.ndarray, kw: dict) -> None:
    buf.seek(0)
    buf.truncate()
    if kw.get("store"):
        buf.write(encode_raw(arr, {}) if arr.dtype == np.uint16 else encode_dark(arr, {}))
    else:
        tifffile.imwrite(buf, arr, maxworkers=1, **kw)


def _readers(data: bytes, arr: np.ndarray, tmp: Path) -> tuple[bool, bool]:
    p = tmp / "probe.tiff"
    p.write_bytes(data)
    try:
        pil = np.array_equal(np.asarray(Image.open(p)), arr)
    except Exception:  # a reader that cannot decode the codec
        pil = False
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    return pil, img is not None and np.array_equal(img, arr)


def bench_codecs(repeat: int, tmp: Path) -> list[str]:
    frames, dark_frames = sim_frames()
    lines = ["| codec | MB / frame (min–max) | ratio | write ms | read ms | Pillow | OpenCV |",
             "|---|---|---|---|---|---|---|"]
    base = None
    for name, kw in CODECS:
        sizes, wr, rd = [], [], []
        readers = (True, True)
        for arr in frames.values():
            buf = io.BytesIO()
            wr.append(_time(lambda arr=arr, buf=buf, kw=kw: _write(buf, arr, kw), repeat))
            data = buf.getvalue()
            sizes.append(len(data))
            rd.append(_time(lambda data=data: tifffile.imread(io.BytesIO(data), maxworkers=1), repeat))
            assert np.array_equal(tifffile.imread(io.BytesIO(data)), arr)
            readers = tuple(a and b for a, b in zip(readers, _readers(data, arr, tmp), strict=True))
        mean = float(np.mean(sizes))
        base = base or mean
        lines.append(f"| {name} | {mean / 1e6:.2f} ({min(sizes) / 1e6:.2f}–{max(sizes) / 1e6:.2f}) | "
                     f"{base / mean:.2f} | {statistics.median(wr):.1f} | {statistics.median(rd):.1f} | "
                     f"{'yes' if readers[0] else 'no'} | {'yes' if readers[1] else 'no'} |")
    from m2s2hil.processing.dark import build_master_dark

    master = build_master_dark(dark_frames, exposure_s=DEFAULT_EXPOSURE_S["weak"], gain=1.0,
                               temperature_c=30.0)
    lines += ["", "| master dark (8 frames, rounded mean) | bytes | write ms |", "|---|---|---|"]
    for name, arr, kw in (("float32, uncompressed (legacy)", master.data.astype(np.float32), {}),
                          ("uint16, deflate 1 (the store's)", master.data, {"store": True})):
        buf = io.BytesIO()
        t = _time(lambda arr=arr, buf=buf, kw=kw: _write(buf, arr, kw), repeat)
        lines.append(f"| {name} | {len(buf.getvalue()) / 1e6:.2f} MB | {t:.1f} |")
    means = ", ".join(f"{k[1]} {v.mean():.0f}" for k, v in list(frames.items())[::2][:3])
    lines.append(f"\nframes: {len(frames)} (voyager B3 and hubble B2 × weak/strong/directional × 2 "
                 f"azimuths); mean DN of voyager's: {means}")
    return lines


def rig_config(fmt: str, size: int = 2048) -> RigConfig:
    cfg = default_rig()
    model = cfg.camera.model.model_copy(update={"width": size, "height": size})
    return cfg.model_copy(update={"camera": cfg.camera.model_copy(update={"model": model}),
                                  "storage": StorageConfig(format=fmt)})  # type: ignore[arg-type]


def run_build(fmt: str, root: Path, sweep: Sweep) -> dict:
    from m2s2hil.engine.build import build_run
    from m2s2hil.rig.factory import open_simulated_rig

    cfg = rig_config(fmt)
    rig = open_simulated_rig(cfg)
    try:
        # the one builder of a run; capture-time QC off: this measures storage, in both formats alike
        engine = build_run(rig, root, sweep=sweep)
        store = engine.store
        t = time.perf_counter()
        st = engine.run()
        wall = time.perf_counter() - t
        frames = len(store.frames())
        path = store.path
        store.close()
    finally:
        rig.close()
    ps = engine.pipeline_stats()
    total = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    return {"format": fmt, "wall_s": wall, "efficiency": st.efficiency, "frames": frames, "bytes": total,
            "per_frame_mb": total / frames / 1e6, "store_s": ps.store_s, "process_s": ps.process_s,
            "path": path}


def build_in_subprocess(fmt: str, root: Path) -> dict:
    """One build in a fresh interpreter (``--one``): no heap or cache state carried over from
    the build before, whichever format it was."""
    out = subprocess.run([sys.executable, __file__, "--one", fmt, "--root", str(root)],
                         check=True, capture_output=True, text=True).stdout
    r = json.loads(out.strip().splitlines()[-1])
    r["path"] = Path(r["path"])
    return r


def bench_cube(store_path: Path, repeat: int) -> list[str]:
    from m2s2hil.store.session import SessionStore

    lines = ["| cube of one 2048² frame | ms |", "|---|---|"]
    with SessionStore.open_path(store_path) as st:
        frames = st.frames()[:20]
        st.read_cube(frames[0].event_id)  # processors built once per dark
        t = statistics.median(_time(lambda fr=fr: st.read_cube(fr.event_id), repeat) for fr in frames)
        lines.append(f"| computed from raw + dark (`read_cube`, compressed session) | {t:.1f} |")
        rd = _time(lambda: st.read_raw(frames[0].event_id), repeat)
        lines.append(f"| of which reading the deflate raw (`read_raw`, sha256 checked) | {rd:.1f} |")
        cube = st.read_cube(frames[0].event_id)
        data = io.BytesIO()
        tifffile.imwrite(data, cube)
        blob = data.getvalue()
        lines.append(f"| decoding a stored float32 cube (legacy, {len(blob) / 1e6:.1f} MB) | "
                     f"{_time(lambda: tifffile.imread(io.BytesIO(blob)), repeat):.1f} |")
    return lines


def describe_load() -> str:
    return f"load average {os.getloadavg()[0]:.1f}"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", default="codecs,cube,build")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=1, help="build both formats this many times, alternating")
    ap.add_argument("--one", choices=("legacy", "compressed"), help=argparse.SUPPRESS)
    ap.add_argument("--root", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:  # a child of build_in_subprocess: one build, its figures as one JSON line
        r = run_build(args.one, args.root, Sweep(satellite="voyager", build="B3"))
        print(json.dumps({**r, "path": str(r["path"])}))
        return
    only = set(args.only.split(","))
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)  # the zstd probes fail loudly
    print(describe_machine())
    tmp = Path(tempfile.mkdtemp(prefix="bench-storage-"))
    try:
        if "codecs" in only:
            print("\n".join(bench_codecs(args.repeat, tmp)))
        if only & {"build", "cube"}:
            results = []
            for k in range(args.rounds):  # same machine, one process a build; the order alternates
                order = ("legacy", "compressed") if k % 2 == 0 else ("compressed", "legacy")
                for fmt in order:
                    r = build_in_subprocess(fmt, tmp / f"{fmt}{k}")
                    r["round"] = k + 1
                    results.append(r)
                    print(f"{fmt}: {r['wall_s']:.1f} s wall ({describe_load()})", flush=True)
                    if fmt == "legacy" or k < args.rounds - 1:
                        shutil.rmtree(r["path"])  # 6 GB; the numbers are kept
                    # Every build starts with nothing of the last one still being written back
                    # or freed (a legacy build leaves gigabytes): untimed.
                    os.sync()
                    time.sleep(SETTLE_S)
            if "build" in only:
                print("\n| round | format | wall time | efficiency | frames | written | bytes / frame "
                      "| storage threads |")
                print("|---|---|---|---|---|---|---|---|")
                for r in results:
                    print(f"| {r['round']} | {r['format']} | {r['wall_s']:.1f} s | {r['efficiency']:.3f} | "
                          f"{r['frames']} | {r['bytes'] / 1e9:.2f} GB | {r['per_frame_mb']:.2f} MB | "
                          f"{r['store_s']:.1f} s |")
                ups = []
                for k in range(args.rounds):
                    pair = {r["format"]: r for r in results if r["round"] == k + 1}
                    old, new = pair["legacy"], pair["compressed"]
                    ups.append(old["wall_s"] / new["wall_s"])
                    print(f"round {k + 1}: speed-up (wall) {ups[-1]:.2f}x; "
                          f"size {old['bytes'] / new['bytes']:.2f}x smaller")
                walls = {f: statistics.median(r["wall_s"] for r in results if r["format"] == f)
                         for f in ("legacy", "compressed")}
                print(f"median wall: legacy {walls['legacy']:.1f} s, compressed {walls['compressed']:.1f} s "
                      f"({walls['legacy'] / walls['compressed']:.2f}x); median of the rounds' speed-ups "
                      f"{statistics.median(ups):.2f}x")
            if "cube" in only:
                last = next(r for r in reversed(results) if r["format"] == "compressed")
                print("\n".join(bench_cube(last["path"], args.repeat)))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
