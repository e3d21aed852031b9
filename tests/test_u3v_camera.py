"""The U3V driver against the simulated TOUCAN, through the real pyusb API.

Every test opens the camera with ``usb.core.find`` over :class:`SimUsbBackend`; the
driver's own I/O is never mocked. Most tests use a 64x64 sensor on a virtual clock.
"""

from __future__ import annotations

import errno
import itertools

import numpy as np
import pytest
import usb.core
from m2s2hil.drivers.errors import CameraError, DeviceGone, DeviceTimeout, FrameCorrupt, FrameIncomplete
from m2s2hil.drivers.interfaces import Camera
from m2s2hil.drivers.u3v import U3VCamera
from m2s2hil.drivers.u3v_control import GenCPError
from m2s2hil.protocols import u3v
from m2s2hil.simulators.fault_injection import FaultPlan
from m2s2hil.simulators.toucan import ToucanCamera
from m2s2hil.simulators.toucan_register_map import FEATURES_ADDRESS, REGISTERS, Access, FeatureReg
from m2s2hil.simulators.toucan_render import GradientSource
from m2s2hil.simulators.u3v_backend import SimUsbBackend

W = H = 64


class RecordingSource:
    """A frame source that remembers what it was asked for and varies per call."""

    def __init__(self, width: int, height: int) -> None:
        self.calls: list[tuple[float, float]] = []
        self.images: list[np.ndarray] = []
        self.shape = (height, width)

    def capture(self, exposure_s: float, gain: float) -> np.ndarray:
        self.calls.append((exposure_s, gain))
        n = len(self.calls)
        img = ((np.arange(self.shape[0] * self.shape[1]) * 7 + n) % 1024).astype(np.uint16)
        self.images.append(img.reshape(self.shape))
        return self.images[-1]


def make(vclock, serial="TC-1", **kw):
    kw.setdefault("width", W)
    kw.setdefault("height", H)
    sim = ToucanCamera(clock=vclock, serial=serial, **kw)
    return sim, SimUsbBackend(sim)


@pytest.fixture
def rig(vclock):
    sim, backend = make(vclock)
    cam = U3VCamera.open(backend=backend, clock=vclock)
    yield sim, backend, cam
    cam.close()


# -- discovery and features ------------------------------------------------------------


def test_discovery_by_class_and_by_ids_and_serial(vclock):
    a = ToucanCamera(clock=vclock, serial="A-1", width=W, height=H)
    b = ToucanCamera(clock=vclock, serial="B-2", width=W, height=H, product_id=0x0002)
    backend = SimUsbBackend(a, b)
    found = list(usb.core.find(find_all=True, backend=backend))
    assert [d.bDeviceClass for d in found] == [0xEF, 0xEF]

    with U3VCamera.open(backend=backend, clock=vclock) as cam:  # by U3V interface class
        assert cam.serial == "A-1"
    with U3VCamera.open(backend=backend, clock=vclock, serial="B-2") as cam:
        assert cam.serial == "B-2"
        assert cam.features.get("DeviceSerialNumber") == "B-2"
    with U3VCamera.open(backend=backend, clock=vclock, vendor_id=0x1209, product_id=0x0002) as cam:
        assert cam.serial == "B-2"
    with pytest.raises(DeviceGone, match="serial=C-3"):
        U3VCamera.open(backend=backend, clock=vclock, serial="C-3")
    with pytest.raises(DeviceGone):
        U3VCamera.open(backend=backend, clock=vclock, vendor_id=0xDEAD)


def test_is_a_camera_and_reads_identity_features(rig):
    sim, _, cam = rig
    assert isinstance(cam, Camera)
    f = cam.features
    assert (f.get("DeviceVendorName"), f.get("DeviceModelName")) == ("SILIOS", "TOUCAN")
    assert f.get("DeviceSerialNumber") == sim.serial
    assert (cam.width, cam.height) == (W, H)
    assert cam.pixel_format == "Mono10"
    assert f.get("PayloadSize") == W * H * 2
    assert not cam.manifest.is_zip
    info = cam.device_info  # the U3V device-info descriptor was found and parsed
    assert info is not None and info.i_serial == 3


def test_exposure_and_gain_round_trip(rig):
    sim, _, cam = rig
    cam.configure(exposure_s=0.0125, gain=2.5)
    assert sim.settings.exposure_us == pytest.approx(12_500.0)
    assert sim.settings.gain == pytest.approx(2.5)
    assert cam.features.get("ExposureTime", fresh=True) == pytest.approx(12_500.0)
    assert cam.settings.exposure_s == pytest.approx(0.0125)


def test_out_of_range_exposure_is_refused_before_the_wire(rig):
    sim, _, cam = rig
    before = len(sim.commands)
    with pytest.raises(CameraError, match="ExposureTime"):
        cam.configure(exposure_s=10e-6)  # below 100 µs
    writes = [c for c in sim.commands[before:] if c.command_id == u3v.CommandId.WRITEMEM_CMD]
    assert writes == []
    assert sim.settings.exposure_us == pytest.approx(10_000.0)
    with pytest.raises(CameraError):
        cam.configure(gain=-1.0)


def test_temperature_is_never_cached(rig):
    sim, _, cam = rig
    sim.temperature_c = 41.5
    assert cam.temperature_c() == pytest.approx(41.5)
    sim.temperature_c = lambda: 43.25
    assert cam.temperature_c() == pytest.approx(43.25)


@pytest.mark.parametrize("fmt", ["Mono10", "Mono10p", "Mono12", "Mono16"])
def test_pixel_formats_decode_to_the_source_image(vclock, fmt):
    source = RecordingSource(W, H)
    sim, backend = make(vclock, frame_source=source)
    with U3VCamera.open(backend=backend, clock=vclock) as cam:
        cam.set_pixel_format(fmt)
        assert sim.settings.pixel_format.name == fmt
        assert cam.features.get("PayloadSize") == u3v.payload_size(u3v.pixel_format(fmt), W, H)
        frame = cam.snap()
    assert frame.pixel_format == fmt
    assert frame.data.dtype == np.uint16 and frame.data.shape == (H, W)
    assert len(source.images) == 1
    assert np.array_equal(frame.data, source.images[0])


def test_pixel_format_change_while_triggered_replans_the_stream(rig):
    _, _, cam = rig
    first = cam.snap()
    cam.set_pixel_format("Mono10p")
    second = cam.snap()
    assert second.pixel_format == "Mono10p"
    assert np.array_equal(first.data, second.data)  # same gradient, another wire format
    assert cam.stream_plan.payload_size == W * H * 10 // 8


# -- frames ----------------------------------------------------------------------------


def test_snap_frames_on_software_trigger(vclock):
    source = RecordingSource(W, H)
    sim, backend = make(vclock, frame_source=source)
    with U3VCamera.open(backend=backend, clock=vclock) as cam:
        cam.configure(exposure_s=0.02, gain=2.0)
        frames = [cam.snap() for _ in range(3)]
    assert [f.block_id for f in frames] == [1, 2, 3]
    assert list(sim.sent_block_ids) == [1, 2, 3]
    assert source.calls == [(pytest.approx(0.02), pytest.approx(2.0))] * 3
    assert all(f.exposure_s == pytest.approx(0.02) and f.gain == pytest.approx(2.0) for f in frames)
    assert frames[0].temperature_c == pytest.approx(35.0)
    assert frames[0].timestamp_s < frames[1].timestamp_s < frames[2].timestamp_s
    assert not np.array_equal(frames[0].data, frames[1].data)


def test_a_long_exposure_after_a_short_one_is_not_delayed_by_its_own_length(rig, vclock):
    # The sensor is busy for the previous frame's exposure, not the newly configured one: a 2 s
    # snap right after a 1 ms one must arrive after about 2 s, within exposure + timeout.
    _sim, _, cam = rig
    cam.configure(exposure_s=0.001)
    cam.snap()
    cam.configure(exposure_s=2.0)
    t0 = vclock.monotonic()
    frame = cam.snap(timeout=2.5)
    assert frame.exposure_s == pytest.approx(2.0)
    assert 2.0 <= vclock.monotonic() - t0 < 2.5


def test_continuous_frames_on_a_virtual_clock(vclock):
    sim, backend = make(vclock)
    with U3VCamera.open(backend=backend, clock=vclock) as cam:
        cam.configure(exposure_s=0.001)
        cam.start_stream(fps=20)
        frames = [cam.read_frame() for _ in range(5)]
        cam.stop_stream()
        assert not sim.acquiring
    ids = [f.block_id for f in frames]
    assert ids == list(range(ids[0], ids[0] + 5))
    assert list(sim.sent_block_ids)[-5:] == ids
    gaps = np.diff([f.timestamp_s for f in frames])
    assert np.allclose(gaps, 1 / 20)
    assert cam.missing_block_ids == []


def test_read_frame_needs_start_stream(rig):
    _, _, cam = rig
    with pytest.raises(CameraError, match="start_stream"):
        cam.read_frame()


def test_full_size_frame(vclock):
    _, backend = make(vclock, width=2048, height=2048)
    with U3VCamera.open(backend=backend, clock=vclock) as cam:
        cam.configure(exposure_s=0.05)
        frame = cam.snap()
        plan = cam.stream_plan
    assert frame.data.shape == (2048, 2048)
    assert np.array_equal(frame.data, GradientSource(2048, 2048).capture(0.05, 1.0))
    assert plan.transfer_size * plan.transfer_count + plan.final1_size >= 2048 * 2048 * 2


# -- faults ----------------------------------------------------------------------------


def test_frame_timeout_then_gap_is_recorded(rig):
    sim, _, cam = rig
    cam.snap()
    sim.faults.add("frame_timeout")
    with pytest.raises(DeviceTimeout):
        cam.snap()
    frame = cam.snap()
    assert frame.block_id == 3
    assert cam.missing_block_ids == [2]


def test_a_late_frame_is_never_returned_by_the_next_snap(vclock):
    source = RecordingSource(W, H)
    _, backend = make(vclock, frame_source=source)
    with U3VCamera.open(backend=backend, clock=vclock) as cam:
        cam.configure(exposure_s=1.0)
        with pytest.raises(DeviceTimeout, match="snap"):
            cam.snap(timeout=0.1)  # the frame is still exposing
        vclock.advance(2.0)  # ...and is ready now
        cam.configure(exposure_s=0.01)
        frame = cam.snap()
    assert source.calls == [(pytest.approx(0.01), 1.0)]  # the late frame was discarded unseen
    assert frame.exposure_s == pytest.approx(0.01)


def test_incomplete_payload_is_typed_and_the_stream_resyncs(rig):
    sim, _, cam = rig
    sim.faults.add("incomplete", fraction=0.5)
    with pytest.raises(FrameIncomplete, match="payload bytes"):
        cam.snap()
    assert cam.snap().block_id == 2


def test_incomplete_payload_in_multi_transfer_frames(vclock):
    sim, backend = make(vclock, width=1024, height=1024, faults=FaultPlan())
    with U3VCamera.open(backend=backend, clock=vclock) as cam:
        sim.faults.add("incomplete", fraction=0.3)
        with pytest.raises(FrameIncomplete):
            cam.snap()
        assert cam.snap().block_id == 2


def test_trailer_error_is_frame_corrupt(rig):
    sim, _, cam = rig
    sim.faults.add("trailer_error")
    with pytest.raises(FrameCorrupt, match="DATA_DISCARDED"):
        cam.snap()
    assert cam.snap().block_id == 2


def test_stall_times_out_until_the_stream_is_restarted(rig):
    sim, _, cam = rig
    cam.start_stream(fps=30)
    cam.read_frame()
    sim.faults.add("stall")
    with pytest.raises(DeviceTimeout, match="restart_stream"):
        cam.read_frame(timeout=0.5)
    assert sim.stalled
    cam.restart_stream()
    assert cam.read_frame().data.shape == (H, W)


def test_unplug_while_streaming_then_reconnect(vclock):
    sim, backend = make(vclock)
    cam = U3VCamera.open(backend=backend, clock=vclock)
    cam.configure(exposure_s=0.004, gain=3.0)
    cam.set_pixel_format("Mono10p")
    cam.start_stream()  # as fast as the camera goes (65 fps)
    got = [cam.read_frame().block_id for _ in range(3)]
    sim.faults.add("unplug", duration_s=0.5)
    with pytest.raises(DeviceGone):
        cam.read_frame()
    # gone from the bus, as libusb would see it
    assert usb.core.find(backend=backend) is None
    with pytest.raises(DeviceGone):
        cam.temperature_c()
    vclock.advance(0.5)
    assert usb.core.find(backend=backend) is not None  # back on the bus, freshly powered on:
    assert sim.settings.exposure_us == pytest.approx(10_000.0)  # defaults, not what we set
    assert not sim.acquiring
    report = cam.reconnect()
    assert report.serial == "TC-1"
    assert report.lost_block_ids == (got[-1] + 1,)
    assert report.downtime_s >= 0.5
    assert report.reapplied["ExposureTime"] == pytest.approx(4000.0)
    assert report.resumed_mode == "streaming"
    # the rebooted device got the settings back
    assert sim.settings.exposure_us == pytest.approx(4000.0)
    assert sim.settings.gain == pytest.approx(3.0)
    assert sim.settings.pixel_format is u3v.PixelFormat.Mono10p
    assert sim.acquiring
    frame = cam.read_frame()
    assert frame.pixel_format == "Mono10p" and frame.block_id == 1  # a fresh device counts anew
    assert cam.missing_block_ids == [got[-1] + 1]
    cam.close()


def test_unplug_during_snap_then_reconnect_rearms_the_trigger(rig):
    sim, _, cam = rig
    cam.configure(exposure_s=0.01)
    cam.snap()
    sim.faults.add("unplug", duration_s=2.0)
    with pytest.raises(DeviceGone):
        cam.snap()
    report = cam.reconnect()
    assert report.lost_block_ids == (2,)
    assert report.reapplied["mode"] == "triggered"
    assert sim.settings.trigger_mode == 1 and sim.acquiring
    assert cam.snap().block_id == 1


def test_reconnect_gives_up_with_device_gone_and_can_be_retried(rig, vclock):
    sim, _, cam = rig
    cam.snap()
    sim.unplug(duration_s=60.0)
    with pytest.raises(DeviceGone):
        cam.snap()
    with pytest.raises(DeviceGone, match="did not come back"):
        cam.reconnect(timeout_s=1.0)
    with pytest.raises(DeviceGone, match="reconnect"):
        cam.temperature_c()
    vclock.advance(60.0)
    report = cam.reconnect(timeout_s=1.0)
    assert report.lost_block_ids == (2,)  # remembered across the failed attempt
    assert report.downtime_s >= 60.0
    assert cam.snap().block_id == 1


def test_usb_errors_through_pyusb_are_enodev_when_unplugged(vclock):
    sim, backend = make(vclock)
    dev = usb.core.find(backend=backend)
    dev.set_configuration()
    sim.unplug(duration_s=1.0)
    with pytest.raises(usb.core.USBError) as info:
        dev.write(0x01, u3v.read_mem(0, 4, 1).encode(), 100)
    assert info.value.errno == errno.ENODEV
    vclock.advance(1.0)
    assert usb.core.find(backend=backend) is not None  # re-enumerated...
    with pytest.raises(usb.core.USBError):  # ...as a new device: the old handle stays dead
        dev.write(0x01, u3v.read_mem(0, 4, 1).encode(), 100)


def test_a_buffer_smaller_than_the_transfer_overflows_like_libusb(vclock):
    _, backend = make(vclock)
    dev = usb.core.find(backend=backend)
    dev.write(0x01, u3v.read_mem(u3v.ABRM.MODEL_NAME, 64, 1).encode(), 100)
    with pytest.raises(usb.core.USBError) as info:
        dev.read(0x81, 16, 100)  # the acknowledge is 12 + 64 bytes
    assert info.value.errno == errno.EOVERFLOW


def test_without_a_backend_the_real_usb_stack_is_searched(vclock):
    # Same code path as on the bench: libusb (if installed) finds no such camera here.
    with pytest.raises((DeviceGone, CameraError)):
        U3VCamera.open(serial="no-such-camera-serial", clock=vclock, timeout_s=0.5)


# -- GenCP -----------------------------------------------------------------------------


def test_pending_ack_extends_the_wait(vclock):
    _, backend = make(vclock, start_delay_s=3.0)  # longer than the 2 s command timeout
    with U3VCamera.open(backend=backend, clock=vclock, timeout_s=2.0) as cam:
        t0 = vclock.monotonic()
        frame = cam.snap()
        assert vclock.monotonic() - t0 >= 3.0
        assert cam.control.pending_acks == 1
        assert cam.control.resends == 0
    assert frame.block_id == 1


def test_lost_acknowledge_is_resent_and_executed_once(rig):
    sim, _, cam = rig
    sim.faults.add("drop_reply")
    cam.configure(exposure_s=0.03)
    assert cam.control.resends == 1
    writes = [c for c in sim.commands if c.command_id == u3v.CommandId.WRITEMEM_CMD]
    writes = [c for c in writes if u3v.parse_write_mem(c)[0] == FeatureReg.EXPOSURE_TIME]
    assert [w.is_resend for w in writes] == [False, True]
    assert writes[0].request_id == writes[1].request_id
    assert sim.settings.exposure_us == pytest.approx(30_000.0)


def test_error_statuses_are_named(rig):
    _, _, cam = rig
    control = cam.control
    with pytest.raises(GenCPError, match="INVALID_ADDRESS") as info:
        control.read(0x7000_0000, 4)
    assert info.value.status == u3v.Status.INVALID_ADDRESS
    with pytest.raises(GenCPError, match="WRITE_PROTECT"):
        control.write_u32(FeatureReg.WIDTH, 10)
    with pytest.raises(GenCPError, match="ACCESS_DENIED"):
        cam.features.execute("TriggerSoftware")  # not acquiring


def test_streaming_locks_the_pixel_format_on_the_device(rig):
    _, _, cam = rig
    cam.start_stream(fps=10)
    with pytest.raises(GenCPError, match="ACCESS_DENIED"):
        cam.features.set("PixelFormat", "Mono12")
    assert cam.features.get("PixelFormat") == "Mono10"  # what the device has, not what was refused
    cam.set_pixel_format("Mono12")  # the driver's way: stop, change, re-plan, restart
    assert cam.read_frame().pixel_format == "Mono12"


def test_zip_manifest(vclock):
    sim, backend = make(vclock, zip_xml=True)
    with U3VCamera.open(backend=backend, clock=vclock) as cam:
        assert cam.manifest.is_zip
        assert cam.manifest.size == len(sim.served_file())
        assert cam.features.get("DeviceModelName") == "TOUCAN"
        assert cam.snap().data.shape == (H, W)


def test_device_capability_says_what_the_camera_has(rig):
    """The ABRM capability bits, read through the driver's control channel, match what the
    device really answers: a family name, an SBRM, a writable user name, the timestamp and
    endianness registers; no message channel, no stacked commands."""
    from m2s2hil.protocols.u3v_bootstrap import DeviceCapability as Cap
    from m2s2hil.protocols.u3v_bootstrap import StringEncoding, decode_device_capability

    _, _, cam = rig
    control = cam.control
    flags, encoding = decode_device_capability(control.read_u64(u3v.ABRM.DEVICE_CAPABILITY))
    assert encoding == StringEncoding.ASCII
    assert flags == (Cap.USER_DEFINED_NAME | Cap.TIMESTAMP | Cap.FAMILY_NAME | Cap.SBRM
                     | Cap.ENDIANNESS_REGISTER | Cap.WRITTEN_LENGTH_FIELD)
    assert u3v.decode_string(control.read(u3v.ABRM.FAMILY_NAME, u3v.STRING_LENGTH)) == "TOUCAN"
    sbrm = control.read_u64(u3v.ABRM.SBRM_ADDRESS)
    assert control.read_u32(sbrm + u3v.SBRM.NUM_STREAM_CHANNELS) == 1
    control.write(u3v.ABRM.USER_DEFINED_NAME, u3v.encode_string("bench-2"))
    assert u3v.decode_string(control.read(u3v.ABRM.USER_DEFINED_NAME, u3v.STRING_LENGTH)) == "bench-2"
    assert control.read_u32(u3v.ABRM.PROTOCOL_ENDIANNESS) == 0xFFFFFFFF
    assert control.read_u64(u3v.ABRM.TIMESTAMP_INCREMENT) == 1


# -- the register table ----------------------------------------------------------------


def test_register_table_has_no_overlapping_registers():
    regs = sorted(REGISTERS, key=lambda r: r.address)
    assert len({r.name for r in regs}) == len(regs)
    for a, b in itertools.pairwise(regs):
        assert a.address + a.width <= b.address, f"{a.name} (0x{a.address:X}, {a.width} B) overlaps {b.name}"
    assert all(r.source for r in regs)  # each fact says where it comes from


def test_feature_registers_sit_where_the_genicam_xml_says():
    import importlib.resources
    import xml.etree.ElementTree as ET

    xml = importlib.resources.files("m2s2hil.simulators").joinpath("data", "toucan_genicam.xml").read_bytes()
    root = ET.fromstring(xml)
    ns = root.tag.split("}")[0] + "}" if root.tag.startswith("{") else ""
    in_xml = {el.get("Name"): int(el.findtext(f"{ns}Address") or "-1", 0)
              for el in root.iter() if el.findtext(f"{ns}Address") is not None}
    features = [r for r in REGISTERS if r.address >= FEATURES_ADDRESS]
    assert {r.name: r.address for r in features} == {r.name: in_xml[f"{r.name}Reg"] for r in features}


def test_every_register_answers_its_documented_default_through_the_driver(vclock):
    """A camera built with the constructor's defaults, read through the driver right after it
    opened: each readable register holds the table's default; a read-only one refuses a write
    and keeps it, a writable one takes its default back."""
    sim = ToucanCamera(clock=vclock)
    with U3VCamera.open(backend=SimUsbBackend(sim), clock=vclock) as cam:
        control = cam.control
        for reg in REGISTERS:
            if not reg.readable:
                continue
            assert reg.decode(control.read(reg.address, reg.width)) == reg.default, reg.name
            if reg.access is Access.RO:
                with pytest.raises(GenCPError):
                    control.write(reg.address, reg.encode(reg.default))
            else:
                control.write(reg.address, reg.encode(reg.default))
            assert reg.decode(control.read(reg.address, reg.width)) == reg.default, reg.name
