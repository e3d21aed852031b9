"""``m2s2hil sim``: the simulated rig."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(help="Simulated devices.", no_args_is_help=True)


@app.command("snapshot")
def snapshot(
    sat: str = typer.Option("voyager", "--sat", help="satellite: voyager, iss, hubble"),
    build: str = typer.Option("B3", "--build", help="build: B1, B2, B3"),
    az: float = typer.Option(0.0, "--az", help="turntable azimuth, degrees"),
    tilt: str = typer.Option("E1", "--tilt", help="elevation E0/E1/E2 (angles from the rig config)"),
    light: str = typer.Option("strong", "--light", help="lighting: weak, strong, directional"),
    out: Path = typer.Option(Path("."), "--out", help="output directory"),
    exposure_ms: float | None = typer.Option(None, "--exposure-ms", help="exposure; default: auto"),
    gain: float = typer.Option(1.0, "--gain", help="linear analog gain"),
    spot_angle: float | None = typer.Option(
        None, "--spot-angle", help="spotlight incidence from the camera axis (default: the rig file's, 45)"
    ),
    temperature: float | None = typer.Option(
        None, "--temperature", help="sensor temperature, °C (default: the rig file's, 35)"
    ),
    seed: int = typer.Option(0, "--seed", help="sensor noise / fixed-pattern seed"),
    rig: Path | None = typer.Option(None, "--rig", help="rig TOML (default: built-in simulated rig)"),
    panel_width: int | None = typer.Option(None, "--panel-width", help="also write a side-by-side panel PNG"),
) -> None:
    """Render one simulated TOUCAN frame: a false-colour PNG and a label-map PNG."""
    import numpy as np

    from m2s2hil.catalog import load_catalog
    from m2s2hil.config import load_rig
    from m2s2hil.errors import UsageError
    from m2s2hil.sim_config import build_frame_source, build_world
    from m2s2hil.simulators.clock import VirtualClock
    from m2s2hil.simulators.scene import SceneError
    from m2s2hil.simulators.snapshot import write_snapshot

    cat = load_catalog()
    cfg = load_rig(rig)
    b = cat.build(sat, build)
    elev = cat.elevation(tilt)
    cond = cat.light(light)
    if exposure_ms is not None and not 0.1 <= exposure_ms <= 5000:
        raise UsageError(f"--exposure-ms {exposure_ms} is outside the TOUCAN's 0.1 … 5000 ms")
    if not gain > 0:
        raise UsageError(f"--gain must be positive, got {gain}")
    if spot_angle is not None and not -90 < spot_angle < 90:
        raise UsageError(f"--spot-angle {spot_angle} must be between -90 and 90 degrees")

    clock = VirtualClock()
    world = build_world(cfg, clock, spot_angle_deg=spot_angle, sensor_temperature_c=temperature)
    world.mount(b.satellite, b.key)
    tilt_deg = cfg.elevations[elev.key]
    world.attach_axis("turntable", lambda: az)
    world.attach_axis("tilt", lambda: tilt_deg)
    for ch in cfg.lamp_channels(cond.key):
        world.set_lamp(ch, True)
    clock.advance(cfg.warmup_s(cond.key) + 0.01)  # let the lamps reach full output

    model = cfg.camera.model
    try:
        source = build_frame_source(cfg, world, seed=seed)
        exposure_s = 5e-3 if exposure_ms is None else exposure_ms / 1000.0
        frame = source.capture(exposure_s, gain)
        if exposure_ms is None:
            # Auto exposure: brightest 0.5 % of the mockup at ~75 % of the range.
            truth = source.truth()
            sig = truth.signal()[truth.labels > 0]
            top = float(np.percentile(sig, 99.5)) if sig.size else 0.0
            if top > 0:
                exposure_s = float(np.clip(exposure_s * 0.75 * model.full_scale / top, 1e-4, 5.0))
                frame = source.capture(exposure_s, gain)
        truth = source.truth()
        world.set_lens_cap(True)
        dark = source.capture(exposure_s, gain)
        world.set_lens_cap(False)
    except SceneError as exc:
        raise UsageError(str(exc)) from None

    stem = f"{b.satellite}_{b.key}_{elev.key}_{cond.key}_az{az:g}"
    caption = (f"{cat.satellite(b.satellite).name} {b.key} {elev.key} ({tilt_deg:g}°) az {az:g}° "
               f"{cond.name}, {exposure_s * 1e3:.2f} ms")
    paths = write_snapshot(
        out, stem, frame, dark, truth.labels, truth.class_names, model.layout, model.bands_nm,
        white=source.band_response, caption=caption, panel_width=panel_width,
    )
    typer.echo(f"{caption}")
    for kind, p in paths.items():
        typer.echo(f"{kind}: {p}")
