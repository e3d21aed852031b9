"""GenICam on top of GenCP: fetch the device's XML through the manifest, load it into
``genicam.genapi.NodeMap`` and reach the device through a Python ``AbstractPort``.

Pitfalls of the binding handled here:

- the node cache is write-through: volatile registers must be ``NoCache`` in the XML,
  and after a failed write every node is invalidated so no cached value lies;
- a command's ``is_done()`` reads its register back, so command registers must be
  readable;
- the NodeMap keeps only a borrowed reference to the port: :class:`Features` holds it;
- a ZIP manifest entry is unzipped here (``zipfile``) before loading, because
  ``load_xml_from_zip_file`` only takes a path;
- ``read(address, length)`` must return exactly ``length`` bytes.
"""

from __future__ import annotations

import hashlib
import io
import zipfile
from typing import Any

from genicam import genapi
from m2s2hil.drivers.errors import CameraError, DeviceError, ProtocolError
from m2s2hil.protocols import u3v
from m2s2hil.protocols.errors import CodecError

MAX_XML_BYTES = 16 * 1024 * 1024  # a device description larger than this is garbage


class GenCPPort(genapi.AbstractPort):
    """The GenApi port: register reads and writes through a :class:`GenCPControl`."""

    def __init__(self, control: Any) -> None:
        super().__init__()
        self.control = control
        self.reads = 0
        self.writes = 0

    def read(self, address: int, length: int) -> bytes:
        data = self.control.read(address, length)
        self.reads += 1
        if len(data) != length:  # GenApi refuses anything else
            raise ProtocolError(f"port read of {length} bytes gave {len(data)}", device=self.control.name)
        return data

    def write(self, address: int, data: bytes) -> None:
        self.control.write(address, bytes(data))
        self.writes += 1

    def get_access_mode(self) -> Any:
        # Not dead: GenApi calls the port's GetAccessMode through the SWIG director before
        # it reads a register; without it the node map fails with "SWIG director pure
        # virtual method called ... GetAccessMode".
        return genapi.EAccessMode.RW


def fetch_device_xml(control: Any) -> tuple[str, u3v.ManifestEntry]:
    """The device description (text) named by the first usable manifest entry."""
    name = control.name
    table = control.read_u64(u3v.ABRM.MANIFEST_TABLE_ADDRESS)
    try:
        count = u3v.manifest_count(control.read(table, 8))
        entries = u3v.decode_manifest(control.read(table, 8 + count * u3v.MANIFEST_ENTRY_SIZE))
    except CodecError as exc:
        raise ProtocolError(f"manifest table at 0x{table:X}: {exc}", device=name) from exc
    if not entries:
        raise CameraError("the manifest table lists no device description file", device=name)
    entry = max(entries, key=lambda e: e.schema[0] == 1)  # prefer a GenApi 1.x file
    if not 0 < entry.size <= MAX_XML_BYTES:
        raise ProtocolError(f"device description of {entry.size} bytes", device=name)
    blob = control.read(entry.address, entry.size)
    if entry.sha1 is not None and hashlib.sha1(blob).digest() != entry.sha1:
        raise ProtocolError("device description fails its SHA-1 check", device=name)
    if entry.is_zip:
        blob = _unzip(blob, name)
    try:
        text = blob.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ProtocolError(f"device description is not UTF-8: {exc}", device=name) from exc
    return text, entry


def _unzip(blob: bytes, device: str) -> bytes:
    try:
        with zipfile.ZipFile(io.BytesIO(blob)) as zf:
            names = [n for n in zf.namelist() if n.lower().endswith(".xml")]
            if not names:
                raise ProtocolError("zipped device description holds no .xml file", device=device)
            return zf.read(names[0])
    except (zipfile.BadZipFile, KeyError, OSError) as exc:
        raise ProtocolError(f"zipped device description is unreadable: {exc}", device=device) from exc


class Features:
    """SFNC features by name, over a NodeMap connected to a :class:`GenCPPort`."""

    def __init__(self, xml: str, control: Any) -> None:
        self.name = control.name
        self.port = GenCPPort(control)  # the NodeMap borrows it: keep it alive here
        self.nodemap = genapi.NodeMap()
        try:
            self.nodemap.load_xml_from_string(xml)
            self.nodemap.connect(self.port, "Device")
        except genapi.GenericException as exc:
            raise CameraError(f"GenICam XML does not load: {exc}", device=self.name) from exc

    def has(self, feature: str) -> bool:
        try:
            self.nodemap.get_node(feature)
        except genapi.GenericException:
            return False
        return True

    def _node(self, feature: str) -> Any:
        try:
            return self.nodemap.get_node(feature)
        except genapi.GenericException as exc:
            raise CameraError(f"the device has no feature {feature!r}", device=self.name) from exc

    def get(self, feature: str, *, fresh: bool = False) -> Any:
        """A feature's value; ``fresh`` bypasses the node cache."""
        node = self._node(feature)
        try:
            if not fresh:
                return node.value
            if isinstance(node, genapi.IEnumeration):
                return node.to_string(False, True)
            return node.get_value(ignore_cache=True)
        except DeviceError:
            raise
        except genapi.GenericException as exc:
            raise CameraError(f"reading {feature}: {exc}", device=self.name, command=feature) from exc

    def set(self, feature: str, value: Any) -> None:
        node = self._node(feature)
        try:
            node.value = value
        except DeviceError:
            self.invalidate()
            raise
        except genapi.GenericException as exc:
            self.invalidate()
            raise CameraError(
                f"setting {feature} = {value!r}: {exc}", device=self.name, command=feature
            ) from exc

    def execute(self, feature: str) -> None:
        node = self._node(feature)
        try:
            node.execute()
        except DeviceError:
            self.invalidate()
            raise
        except genapi.GenericException as exc:
            raise CameraError(f"executing {feature}: {exc}", device=self.name, command=feature) from exc

    def range(self, feature: str) -> tuple[float, float]:
        node = self._node(feature)
        try:
            return node.min, node.max
        except genapi.GenericException as exc:
            raise CameraError(f"range of {feature}: {exc}", device=self.name, command=feature) from exc

    def invalidate(self) -> None:
        """Forget every cached value (after a failed write or a device-side change)."""
        self.nodemap._invalidate_nodes()

    def close(self) -> None:
        self.nodemap.disconnect()
