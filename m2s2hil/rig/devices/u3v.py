"""The USB3 Vision camera (the rig file's ``[camera]``): driver, simulator and ``rig probe``.

``rig probe`` reads model, serial, firmware, sensor size, pixel format and bit depth and holds
them against ``[camera.model]``. No recognition on a wrong port: the camera is found on USB by
vendor, product and serial, not on a serial port.
"""

from __future__ import annotations

import errno
from typing import TYPE_CHECKING, Any

from m2s2hil.drivers.errors import DeviceGone
from m2s2hil.rig.devices.findings import Finding, ProbeReport
from m2s2hil.rig.devices.kind import CameraKind, Setup, SimParts, close_quietly
from m2s2hil.rig.open_errors import RigOpenError, detail_of, errno_of, opening
from m2s2hil.sim_config import camera_sim_name, is_simulated

if TYPE_CHECKING:
    from m2s2hil.drivers.u3v import U3VCamera

_PIXEL_BITS = {"Mono8": 8, "Mono10": 10, "Mono10p": 10, "Mono10Packed": 10, "Mono12": 12, "Mono12p": 12,
               "Mono12Packed": 12, "Mono14": 14, "Mono16": 16}


def _simulator(setup: Setup, parts: SimParts) -> Any:
    from m2s2hil.simulators.toucan import ToucanCamera

    config = setup.config
    model = config.camera.model
    world = parts.world
    return ToucanCamera(
        clock=setup.clock,
        frame_source=parts.frame_source,
        width=model.width,
        height=model.height,
        bit_depth=model.bit_depth,
        faults=parts.faults,
        name=camera_sim_name(config),
        max_fps=model.max_fps,
        temperature_c=lambda: world.sensor_temperature_c,
        serial=config.simulation.camera_serial,
    )


def _open_camera(setup: Setup) -> U3VCamera:
    """Over the in-process simulator of a ``sim://`` port (from ``setup.sims``), else on USB;
    errors as RigOpenError."""
    from m2s2hil.drivers.u3v import U3VCamera

    cam_cfg = setup.config.camera
    with opening(setup.name, cam_cfg.port, "u3v"):
        if is_simulated(cam_cfg.port):
            from m2s2hil.simulators.u3v_backend import SimUsbBackend

            toucan = setup.sims[camera_sim_name(setup.config)]
            return U3VCamera.open(backend=SimUsbBackend(toucan), serial=toucan.serial, clock=setup.clock,
                                  timeout_s=cam_cfg.timeout_s, name=setup.name)
        return U3VCamera.open(vendor_id=cam_cfg.vendor_id, product_id=cam_cfg.product_id,
                              serial=cam_cfg.serial, clock=setup.clock, timeout_s=cam_cfg.timeout_s,
                              name=setup.name)


def _explain(exc: BaseException, device: str, port: str) -> RigOpenError:
    """A camera that did not open: libusb missing, no permission (the udev rule), no camera on
    USB, or an error of the camera itself. Never a serial port's causes."""
    text = str(exc).lower()
    detail = detail_of(exc)
    if "no usb backend" in text or type(exc).__name__ == "NoBackendError":
        return RigOpenError(device, port, "no USB backend", detail)
    if errno_of(exc) in (errno.EACCES, errno.EPERM) or "access denied" in text:
        return RigOpenError(device, port, "permission denied", detail)
    if isinstance(exc, DeviceGone) and "found" in text:
        return RigOpenError(device, port, "no camera", detail)
    return RigOpenError(device, port, "device error", detail)


def _probe(setup: Setup, report: ProbeReport, apply: bool) -> None:
    from m2s2hil.protocols.u3v_bootstrap import ABRM

    cam_cfg = setup.config.camera
    model = cam_cfg.model
    cam = _open_camera(setup)
    try:
        with opening(setup.name, cam_cfg.port, "u3v"):
            vendor = cam.control.read_string(ABRM.MANUFACTURER_NAME)
            name = cam.control.read_string(ABRM.MODEL_NAME)
            version = cam.control.read_string(ABRM.DEVICE_VERSION)
            fmt = cam.pixel_format
            width, height = cam.width, cam.height
        add = report.findings.append
        shown = f"{vendor} {name}".strip()
        ok = name.lower() in model.name.lower() or model.name.lower() in shown.lower()
        add(Finding("camera", "model", model.name, shown, ok, "" if ok else
                    "another camera: the band layout and calibration of the rig file do not apply"))
        add(Finding("camera", "serial", cam_cfg.serial or "", cam.serial or "?",
                    None if cam_cfg.serial is None else cam.serial == cam_cfg.serial))
        add(Finding("camera", "firmware", "", version, None))
        size_ok = (width, height) == (model.width, model.height)
        add(Finding("camera", "sensor size", f"{model.width}x{model.height}", f"{width}x{height}", size_ok,
                    "" if size_ok else "frames do not match the mosaic layout: demosaicking fails"))
        bits = _PIXEL_BITS.get(fmt)
        add(Finding("camera", "pixel format", "", fmt, None))
        bits_ok = bits == model.bit_depth
        add(Finding("camera", "bit depth", str(model.bit_depth), str(bits) if bits else f"? ({fmt})", bits_ok,
                    "" if bits_ok else "full scale differs: saturation and exposure search are wrong"))
    finally:
        close_quietly(cam)


KIND = CameraKind(
    protocol="u3v",
    title="USB3 Vision camera",
    make_simulator=_simulator,
    open_camera=_open_camera,
    probe=_probe,
    explain=_explain,
)
