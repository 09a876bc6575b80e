"""What hardware is plugged in: serial ports, USB devices, I2C buses and video nodes, named where known.

Discovery only reads. It opens no serial port and sends nothing on a bus; the one USB traffic it makes is
the standard GET_DESCRIPTOR request for string descriptors (names and serial numbers), as ``lsusb -v`` does.
What a device *is* comes from the data table :data:`KNOWN_DEVICES` (USB ids and interface classes, with
their sources); each recognized device carries the config snippet that selects its backend.

Serial ports and video nodes are found through sysfs, so the laser and the Dynamixel adapter are recognized
even when libusb is missing or USB access is denied. pyusb adds the devices that have no kernel node
(vendor-SDK and USB3 Vision cameras) and tells whether user-space USB access is allowed.

The port lister, the pyusb backend, ``/dev``, ``/sys`` and the access check are parameters of
:func:`discover`, so tests describe a whole machine without hardware.
"""

from __future__ import annotations

import dataclasses
import enum
import errno
import grp
import logging
import os
import pwd
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.registry import BACKENDS, DeviceKind

__all__ = [
    "KNOWN_DEVICES",
    "Access",
    "DeviceNode",
    "Discovery",
    "KnownDevice",
    "Recognized",
    "SerialPort",
    "Transport",
    "UsbDevice",
    "UsbMatch",
    "UsbScan",
    "check_access",
    "discover",
    "list_i2c_buses",
    "list_serial_ports",
    "list_usb_devices",
    "list_video_devices",
    "match_known",
    "recognize",
    "render_config",
]

log = logging.getLogger(__name__)

AccessCheck = Callable[[str, int], bool]
InterfaceTriple = tuple[int, int, int]

# A stalled device would otherwise hold each string request for pyusb's default 1 s.
STRING_TIMEOUT_MS = 300
USB_CLASS_HUB = 0x09
# Placeholders for the config snippet when discovery cannot know the value.
UNKNOWN_PATH = "<port>"
UNKNOWN_SERIAL = "<unknown>"


class Transport(enum.StrEnum):
    """How the agent reaches a device, which decides where it shows up and what access it needs."""

    SERIAL = "serial"  # a tty made by a kernel driver (cdc_acm, ftdi_sio, cp210x): needs the tty's group
    USB = "usb"  # user-space libusb (vendor SDK, GenTL producer): needs a udev rule for /dev/bus/usb
    V4L2 = "v4l2"  # a /dev/video node made by uvcvideo: needs the 'video' group


@dataclass(frozen=True, slots=True)
class UsbMatch:
    """Which USB devices a table entry claims: one id, every product of a vendor, or an interface class.

    ``interface`` is (class, subclass, protocol); protocol None accepts any.
    """

    vid: int | None = None
    pid: int | None = None
    interface: tuple[int, int, int | None] | None = None

    def matches(self, vid: int | None, pid: int | None, interfaces: Iterable[InterfaceTriple]) -> bool:
        if self.interface is not None:
            want_class, want_sub, want_proto = self.interface
            return any(
                c == want_class and s == want_sub and (want_proto is None or p == want_proto)
                for c, s, p in interfaces
            )
        if self.vid is None or vid != self.vid:
            return False
        return self.pid is None or pid == self.pid

    def describe(self) -> str:
        if self.interface is not None:
            cls, sub, proto = self.interface
            return f"class {cls:02x}/{sub:02x}/{'*' if proto is None else f'{proto:02x}'}"
        vid = "*" if self.vid is None else f"{self.vid:04x}"
        pid = "*" if self.pid is None else f"{self.pid:04x}"
        return f"{vid}:{pid}"


@dataclass(frozen=True, slots=True)
class KnownDevice:
    """One row of the recognition table: what a USB id means for this robot and how to configure it."""

    key: str
    name: str
    detail: str
    match: UsbMatch
    transport: Transport
    kind: DeviceKind | None = None
    backend: str | None = None
    # TOML for the agent's config; "{path}" and "{serial}" are filled in from what was found.
    config: str | None = None
    kernel_driver: str | None = None
    # The id belongs to a common chip or a vendor's stock firmware, so other products share it.
    generic_id: bool = False
    notes: tuple[str, ...] = ()


_FTDI_LATENCY = (
    'set the FTDI latency timer to 1 ms (udev: ATTR{device/latency_timer}="1"); at the default 16 ms '
    "every Dynamixel reply waits up to 16 ms in the adapter"
)
_DXL_CONFIG = '[servos]\nbackend = "dynamixel"\nport = "{path}"\nbaudrate = %d'


# Sources: ../shared/reference/devices.md sections 1, 2, 4 and 7 (udev rules of Hokuyo users, Interbotix,
# ROBOTIS turtlebot3 `turtlebot3_bringup/script/99-turtlebot3-cdc.rules`); USB3 Vision interface codes
# from Aravis `src/arvuvinterfaceprivate.h` (class 0xEF, subclass 0x05; protocol 0 control, 1 event,
# 2 streaming); UVC is the USB-IF Video class 0x0E, subclass 1 = VideoControl.
# The first matching row wins, so exact ids come before vendor-wide rows and those before class rules.
def _mindvision(key: str, vendor_id: int) -> KnownDevice:
    # No config snippet: vlp-agent has no backend for the MindVision SDK, and no MindVision GenTL producer
    # is known (../shared/reference/devices.md section 4), so no [camera] table would drive this camera.
    return KnownDevice(
        key=key,
        name="MindVision camera",
        detail="vendor SDK only (libMVSDK.so + mvsdk.py): not UVC/V4L2, not GenTL",
        match=UsbMatch(vendor_id, None),
        transport=Transport.USB,
        kind=DeviceKind.CAMERA,
        notes=(
            "vlp-agent has no backend for the MindVision SDK: use a USB3 Vision camera (backend "
            '"genicam", through its maker\'s GenTL producer) or a UVC camera (backend "v4l2")',
        ),
    )


KNOWN_DEVICES: tuple[KnownDevice, ...] = (
    KnownDevice(
        key="hokuyo-urg",
        name="Hokuyo URG laser scanner",
        detail="SCIP 2.0 over USB CDC-ACM",
        match=UsbMatch(0x15D1, 0x0000),
        transport=Transport.SERIAL,
        kind=DeviceKind.LASER,
        backend="urg",
        config='[laser]\nbackend = "urg"\nurl = "{path}"',
        kernel_driver="cdc_acm",
        notes=(
            "ModemManager may probe a new ttyACM port with AT commands; a udev rule with "
            'ENV{ID_MM_DEVICE_IGNORE}="1" keeps it away',
        ),
    ),
    KnownDevice(
        key="robotis-u2d2",
        name="ROBOTIS U2D2 Dynamixel adapter",
        detail="FTDI FT232H USB-serial to the Dynamixel bus (XL430 default 57600 bps)",
        match=UsbMatch(0x0403, 0x6014),
        transport=Transport.SERIAL,
        kind=DeviceKind.SERVOS,
        backend="dynamixel",
        config=_DXL_CONFIG % 57600,
        kernel_driver="ftdi_sio",
        generic_id=True,
        notes=(_FTDI_LATENCY,),
    ),
    KnownDevice(
        key="ftdi-ft232r",
        name="FTDI FT232R USB-serial adapter",
        detail="maybe a U2D2-like Dynamixel adapter; many other gadgets use this chip too",
        match=UsbMatch(0x0403, 0x6001),
        transport=Transport.SERIAL,
        kind=DeviceKind.SERVOS,
        backend="dynamixel",
        config="# if this is the Dynamixel adapter:\n" + _DXL_CONFIG % 57600,
        kernel_driver="ftdi_sio",
        generic_id=True,
        notes=(_FTDI_LATENCY, "tell several FT232R apart by serial number (udev: ATTRS{serial})"),
    ),
    KnownDevice(
        key="robotis-opencr",
        name="ROBOTIS OpenCR board",
        detail="STM32 USB CDC-ACM; the TurtleBot3 firmware answers as Dynamixel ID 200 at 1 Mbps",
        match=UsbMatch(0x0483, 0x5740),
        transport=Transport.SERIAL,
        kind=DeviceKind.SERVOS,
        backend="dynamixel",
        config=_DXL_CONFIG % 1_000_000,
        kernel_driver="cdc_acm",
        generic_id=True,
        notes=(
            "with the TurtleBot3 firmware the PC talks to the board (its own control table), not to the "
            "XL430s; the 'dynamixel' backend expects the servos themselves, through a pass-through "
            "firmware or a U2D2",
        ),
    ),
    KnownDevice(
        key="stm32-dfu",
        name="STM32 in DFU bootloader mode",
        detail="an OpenCR (or other STM32 board) waiting for a firmware update; no serial port in this mode",
        match=UsbMatch(0x0483, 0xDF11),
        transport=Transport.USB,
        generic_id=True,
        notes=("finish the update or replug the board to get its serial port back",),
    ),
    KnownDevice(
        key="robotis-opencm904",
        name="ROBOTIS OpenCM9.04 board",
        detail="USB CDC-ACM Dynamixel controller board",
        match=UsbMatch(0xFFF1, 0xFF48),
        transport=Transport.SERIAL,
        kind=DeviceKind.SERVOS,
        backend="dynamixel",
        config=_DXL_CONFIG % 1_000_000,
        kernel_driver="cdc_acm",
        notes=("it is a Dynamixel bus only with a pass-through sketch on the board",),
    ),
    KnownDevice(
        key="silabs-cp210x",
        name="Silicon Labs CP210x USB-UART",
        detail="on a TurtleBot3 the LDS-01 lidar (not SCIP: no vlp-agent backend); also common on RFID "
        "reader and IMU boards",
        match=UsbMatch(0x10C4, 0xEA60),
        transport=Transport.SERIAL,
        config='# if this is the RFID reader ("id12la", "rdm6300" or "mercury"):\n'
        '[rfid]\nbackend = "id12la"\nurl = "{path}"',
        kernel_driver="cp210x",
        generic_id=True,
    ),
    # MindVision ships under two USB vendor ids.
    *(_mindvision(key, vendor) for key, vendor in (("mindvision", 0xF622), ("mindvision-080b", 0x080B))),
    KnownDevice(
        key="usb3vision",
        name="USB3 Vision camera",
        detail="GenICam through harvesters and the camera maker's GenTL producer (.cti)",
        match=UsbMatch(interface=(0xEF, 0x05, 0x00)),
        transport=Transport.USB,
        kind=DeviceKind.CAMERA,
        backend="genicam",
        config='[camera]\nbackend = "genicam"\ncti = "<the camera maker\'s GenTL producer, a .cti file>"\n'
        'serial = "{serial}"',
    ),
    KnownDevice(
        key="uvc",
        name="UVC camera",
        detail="USB Video Class: V4L2 through OpenCV",
        match=UsbMatch(interface=(0x0E, 0x01, None)),
        transport=Transport.V4L2,
        kind=DeviceKind.CAMERA,
        backend="v4l2",
        config='[camera]\nbackend = "v4l2"\ndevice = "{path}"',
        kernel_driver="uvcvideo",
    ),
)


# -- what discovery reports ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Access:
    """Whether this user may open the node read-write. ``ok`` None: could not tell."""

    ok: bool | None
    hint: str | None = None


@dataclass(frozen=True, slots=True)
class SerialPort:
    device: str
    # /dev/serial/by-id/... for the same port: it survives replugging, ttyACM0/1 numbering does not.
    stable_path: str | None
    description: str | None
    vid: int | None
    pid: int | None
    serial_number: str | None
    manufacturer: str | None
    product: str | None
    # USB port path ("1-1.2"), the same string a UsbDevice carries, so the two views can be joined.
    location: str | None
    access: Access

    @property
    def config_path(self) -> str:
        return self.stable_path or self.device


@dataclass(frozen=True, slots=True)
class UsbDevice:
    bus: int | None
    address: int | None
    location: str | None
    vid: int
    pid: int
    device_class: int
    interfaces: tuple[InterfaceTriple, ...]
    manufacturer: str | None
    product: str | None
    serial_number: str | None
    access: Access

    @property
    def is_hub(self) -> bool:
        return self.device_class == USB_CLASS_HUB


@dataclass(frozen=True, slots=True)
class UsbScan:
    devices: tuple[UsbDevice, ...] = ()
    # Why USB could not be listed, or listing stopped early; the rest of discovery still ran.
    error: str | None = None


@dataclass(frozen=True, slots=True)
class DeviceNode:
    """A /dev/i2c-N or /dev/videoN node, with what sysfs says about it."""

    path: str
    number: int  # the N in i2c-N or videoN
    stable_path: str | None
    name: str | None
    access: Access
    vid: int | None = None
    pid: int | None = None
    location: str | None = None
    interface: InterfaceTriple | None = None
    # For video: 0 is a device's capture node; uvcvideo adds a metadata node with index 1.
    index: int | None = None

    @property
    def config_path(self) -> str:
        return self.stable_path or self.path


@dataclass(frozen=True, slots=True)
class Recognized:
    """A device the table knows. ``where`` is for people (a node, or "USB 1-1.2" when it has none);
    ``path`` is what went into ``config`` (the by-id link when there is one), None without a node."""

    known: KnownDevice
    where: str
    path: str | None
    vid: int | None
    pid: int | None
    serial_number: str | None
    location: str | None
    config: str | None
    notes: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class Discovery:
    serial_ports: tuple[SerialPort, ...]
    usb: UsbScan
    i2c_buses: tuple[DeviceNode, ...]
    video_devices: tuple[DeviceNode, ...]
    recognized: tuple[Recognized, ...]
    serial_error: str | None = None

    @property
    def usb_devices(self) -> tuple[UsbDevice, ...]:
        """USB devices without hubs: hubs are plumbing, not hardware anyone configures."""
        return tuple(d for d in self.usb.devices if not d.is_hub)

    @property
    def empty(self) -> bool:
        return not (self.serial_ports or self.usb_devices or self.i2c_buses or self.video_devices)

    def to_dict(self) -> dict[str, Any]:
        """Plain data for JSON; USB ids as the hex strings lsusb prints."""
        return dataclasses.asdict(self, dict_factory=_json_dict)


def _json_dict(items: list[tuple[str, Any]]) -> dict[str, Any]:
    return {
        key: f"{value:04x}" if key in ("vid", "pid") and isinstance(value, int) else value
        for key, value in items
    }


# -- access ---------------------------------------------------------------------------------------------


def _group_name(gid: int) -> str:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


def _user_listed_in(gid: int) -> bool:
    """True when the group database lists us but this process lacks the group: a stale login session."""
    try:
        user = pwd.getpwuid(os.geteuid()).pw_name
        return user in grp.getgrgid(gid).gr_mem
    except KeyError:
        return False


def check_access(path: str, access: AccessCheck = os.access) -> Access:
    """Can we open ``path`` read-write, and if not, what would fix it."""
    if access(path, os.R_OK | os.W_OK):
        return Access(True)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return Access(False, "the device node has gone (unplugged?)")
    except OSError as exc:
        return Access(False, f"cannot check it: {exc.strerror}")
    group = _group_name(st.st_gid)
    if st.st_mode & 0o060 == 0o060 and st.st_gid != 0:
        if _user_listed_in(st.st_gid):
            return Access(
                False,
                f"you are in the '{group}' group, but this login session started before "
                "that: log out and back in",
            )
        return Access(
            False,
            f"add yourself to the '{group}' group: sudo usermod -aG {group} $USER, then log out and back in",
        )
    return Access(
        False,
        f"only root can open it (mode {st.st_mode & 0o777:o}, group {group}): a udev rule "
        'must set GROUP and MODE="0660"',
    )


def _usb_denied_hint(vid: int) -> str:
    return (
        f'permission denied: needs a udev rule, e.g. SUBSYSTEM=="usb", ATTR{{idVendor}}=="{vid:04x}", '
        'MODE="0660", GROUP="plugdev", and your user in plugdev'
    )


# -- sysfs helpers --------------------------------------------------------------------------------------


def _read_sysfs(path: Path) -> str | None:
    try:
        text = path.read_text(encoding="utf-8", errors="replace").strip()
    except OSError:
        return None
    return text or None


def _read_hex(path: Path) -> int | None:
    text = _read_sysfs(path)
    if text is None:
        return None
    try:
        return int(text, 16)
    except ValueError:
        return None


def _stable_links(directory: Path) -> dict[str, str]:
    """Map each real node to its udev by-id symlink (e.g. /dev/serial/by-id/usb-Hokuyo...-if00)."""
    links: dict[str, str] = {}
    try:
        entries = sorted(directory.iterdir())
    except OSError:
        return links
    for entry in entries:
        if entry.is_symlink():
            links.setdefault(os.path.realpath(entry), str(entry))
    return links


def _usb_location(sys_dir: Path) -> str | None:
    """'1-1.2' from a sysfs USB device directory; root hubs ('usb1') have no port path."""
    name = sys_dir.name
    return name if re.fullmatch(r"\d+-[\d.]+", name) else None


def _usb_above(node_device: Path) -> tuple[Path | None, Path | None]:
    """(USB interface dir, USB device dir) above a /sys/class/... device link, or (None, None)."""
    try:
        here = node_device.resolve(strict=True)
    except OSError:
        return None, None
    interface_dir: Path | None = None
    for candidate in (here, *list(here.parents)[:4]):
        if interface_dir is None and (candidate / "bInterfaceClass").is_file():
            interface_dir = candidate
        if (candidate / "idVendor").is_file():
            return interface_dir, candidate
    return None, None


# -- serial ports ---------------------------------------------------------------------------------------


def _uart_absent(name: str, sys_root: Path) -> bool:
    """A ttyS* with no UART behind it.

    Newer kernels (Ubuntu 24.04's 6.8, not 22.04's 6.2) put every legacy ttyS0..31 in the 'serial-base'
    subsystem, so pyserial's filter, which hid the 'platform' ones, now lists all 32 (pyserial issue #763).
    The port's sysfs 'type' is 0 (PORT_UNKNOWN) when no UART was found at that address.
    """
    if not re.fullmatch(r"ttyS\d+", name):
        return False
    return _read_sysfs(sys_root / "class" / "tty" / name / "type") == "0"


def _clean(value: Any) -> str | None:
    if value is None:
        return None
    text = str(value).strip()
    return None if text in ("", "n/a") else text


def list_serial_ports(
    comports: Callable[[], Iterable[Any]] | None = None,
    *,
    dev_root: Path = Path("/dev"),
    sys_root: Path = Path("/sys"),
    access: AccessCheck = os.access,
) -> tuple[SerialPort, ...]:
    """Serial ports from pyserial's ``comports()`` (or any callable returning ListPortInfo-like objects)."""
    if comports is None:
        from serial.tools.list_ports import comports as pyserial_comports

        comports = pyserial_comports
    by_id = _stable_links(dev_root / "serial" / "by-id")
    ports: list[SerialPort] = []
    for info in comports():
        device = str(info.device)
        name = os.path.basename(device)
        vid = info.vid if isinstance(info.vid, int) else None
        if vid is None and _uart_absent(name, sys_root):
            log.debug("skipping %s: no UART behind it", device)
            continue
        location = _clean(getattr(info, "location", None))
        if location is not None:
            # Multi-interface chips report the interface ("1-1.2:1.0"); the device part joins with USB.
            location = location.split(":", 1)[0]
        ports.append(
            SerialPort(
                device=device,
                stable_path=by_id.get(os.path.realpath(device)),
                # pyserial falls back to the port's own name as its description; that says nothing.
                description=None if info.description == name else _clean(info.description),
                vid=vid,
                pid=info.pid if isinstance(info.pid, int) else None,
                serial_number=_clean(info.serial_number),
                manufacturer=_clean(info.manufacturer),
                product=_clean(info.product),
                location=location,
                access=check_access(device, access),
            )
        )
    return tuple(sorted(ports, key=lambda p: p.device))


# -- USB ------------------------------------------------------------------------------------------------


def _libusb_backend() -> tuple[Any, str | None]:
    """pyusb's libusb-1.0 backend, or None and a sentence saying why not."""
    import usb.backend.libusb1
    import usb.libloader

    backend = usb.backend.libusb1.get_backend()
    if backend is not None:
        return backend, None
    # get_backend() says None both when the library is absent and when libusb_init() fails; tell them apart,
    # because the fixes differ (install a package, or give the process /dev/bus/usb).
    if usb.libloader.locate_library(("usb-1.0", "libusb-1.0")) is None:
        return None, "libusb-1.0 is not installed (Debian/Ubuntu: sudo apt install libusb-1.0-0)"
    return None, (
        "libusb-1.0 is installed but would not start; no /dev/bus/usb here "
        "(a container or service without USB access?)"
    )


def _interfaces(dev: Any) -> tuple[InterfaceTriple, ...]:
    import usb.core

    seen: list[InterfaceTriple] = []
    try:
        for cfg in dev:
            for intf in cfg:
                triple = (
                    int(intf.bInterfaceClass),
                    int(intf.bInterfaceSubClass),
                    int(intf.bInterfaceProtocol),
                )
                if triple not in seen:
                    seen.append(triple)
    except (usb.core.USBError, IndexError) as exc:
        log.debug("%04x:%04x: configuration descriptors unreadable: %s", dev.idVendor, dev.idProduct, exc)
    return tuple(seen)


@dataclass(frozen=True, slots=True)
class _Strings:
    manufacturer: str | None = None
    product: str | None = None
    serial_number: str | None = None
    readable: bool | None = None  # the device answered a string request at all
    denied: bool = False


def _read_strings(dev: Any) -> _Strings:
    """Manufacturer, product and serial string descriptors; reading them needs the device opened."""
    import usb.core
    import usb.util

    dev.default_timeout = STRING_TIMEOUT_MS
    try:
        try:
            langids = usb.util.get_langids(dev)
        except usb.core.USBError as exc:
            denied = exc.errno in (errno.EACCES, errno.EPERM)
            log.debug("%04x:%04x: no string descriptors: %s", dev.idVendor, dev.idProduct, exc)
            return _Strings(readable=False, denied=denied)
        if not langids:
            return _Strings(readable=True)
        values: list[str | None] = []
        for index in (dev.iManufacturer, dev.iProduct, dev.iSerialNumber):
            value: str | None = None
            if index:
                try:
                    value = _clean(usb.util.get_string(dev, index, langids[0]))
                except (usb.core.USBError, ValueError) as exc:  # UnicodeDecodeError is a ValueError
                    log.debug("%04x:%04x: string %d unreadable: %s", dev.idVendor, dev.idProduct, index, exc)
            values.append(value)
        manufacturer, product, serial_number = values
        return _Strings(manufacturer, product, serial_number, readable=True)
    finally:
        usb.util.dispose_resources(dev)


def _describe_usb(dev: Any, *, dev_root: Path, sys_root: Path, access: AccessCheck) -> UsbDevice:
    vid, pid = int(dev.idVendor), int(dev.idProduct)
    bus = int(dev.bus) if dev.bus is not None else None
    address = int(dev.address) if dev.address is not None else None
    ports = getattr(dev, "port_numbers", None)
    location = f"{bus}-{'.'.join(str(p) for p in ports)}" if bus is not None and ports else None
    interfaces = _interfaces(dev)
    strings = _read_strings(dev)
    manufacturer, product, serial = strings.manufacturer, strings.product, strings.serial_number
    if location is not None and not strings.readable:
        # sysfs keeps a world-readable copy of the strings, so an access-denied device still gets a name.
        sys_dir = sys_root / "bus" / "usb" / "devices" / location
        manufacturer = manufacturer or _read_sysfs(sys_dir / "manufacturer")
        product = product or _read_sysfs(sys_dir / "product")
        serial = serial or _read_sysfs(sys_dir / "serial")

    # libusb opens /dev/bus/usb/BBB/DDD read-write; when the node is visible, its mode is the answer.
    node = dev_root / "bus" / "usb" / f"{bus:03d}" / f"{address:03d}" if bus and address else None
    if node is not None and node.exists():
        ok = access(str(node), os.R_OK | os.W_OK)
        usb_access = Access(ok, None if ok else _usb_denied_hint(vid))
    elif strings.denied:
        usb_access = Access(False, _usb_denied_hint(vid))
    else:
        usb_access = Access(strings.readable)
    return UsbDevice(
        bus=bus,
        address=address,
        location=location,
        vid=vid,
        pid=pid,
        device_class=int(dev.bDeviceClass),
        interfaces=interfaces,
        manufacturer=manufacturer,
        product=product,
        serial_number=serial,
        access=usb_access,
    )


def list_usb_devices(
    backend: Any = None,
    *,
    dev_root: Path = Path("/dev"),
    sys_root: Path = Path("/sys"),
    access: AccessCheck = os.access,
) -> UsbScan:
    """Every USB device pyusb sees. ``backend`` is a ``usb.backend.IBackend``; None means libusb-1.0."""
    try:
        import usb.core
    except ImportError:
        return UsbScan(error="pyusb is not installed: pip install pyusb")
    if backend is None:
        backend, why = _libusb_backend()
        if backend is None:
            return UsbScan(error=why)
    devices: list[UsbDevice] = []
    try:
        for dev in usb.core.find(find_all=True, backend=backend):
            devices.append(_describe_usb(dev, dev_root=dev_root, sys_root=sys_root, access=access))
    except usb.core.USBError as exc:
        # find() is a generator: one failure ends it, so report what was listed and why it stopped.
        log.debug("USB enumeration failed", exc_info=True)
        return UsbScan(tuple(devices), f"USB listing stopped after {len(devices)} devices: {exc}")
    return UsbScan(tuple(devices))


# -- I2C and video nodes --------------------------------------------------------------------------------


def _numbered_nodes(dev_root: Path, prefix: str) -> list[tuple[int, Path]]:
    pattern = re.compile(re.escape(prefix) + r"(\d+)")
    found: list[tuple[int, Path]] = []
    for path in dev_root.glob(prefix + "*"):
        m = pattern.fullmatch(path.name)
        if m:
            found.append((int(m.group(1)), path))
    return sorted(found)


def list_i2c_buses(
    *, dev_root: Path = Path("/dev"), sys_root: Path = Path("/sys"), access: AccessCheck = os.access
) -> tuple[DeviceNode, ...]:
    """/dev/i2c-N with the adapter's name. Buses are not probed: a stray read can upset some chips."""
    buses: list[DeviceNode] = []
    for number, path in _numbered_nodes(dev_root, "i2c-"):
        name = _read_sysfs(sys_root / "class" / "i2c-dev" / f"i2c-{number}" / "name")
        buses.append(DeviceNode(str(path), number, None, name, check_access(str(path), access)))
    return tuple(buses)


def list_video_devices(
    *, dev_root: Path = Path("/dev"), sys_root: Path = Path("/sys"), access: AccessCheck = os.access
) -> tuple[DeviceNode, ...]:
    """/dev/videoN with its name, node index and, for USB cameras, the USB ids and interface class."""
    by_id = _stable_links(dev_root / "v4l" / "by-id")
    nodes: list[DeviceNode] = []
    for number, path in _numbered_nodes(dev_root, "video"):
        sys_dir = sys_root / "class" / "video4linux" / f"video{number}"
        index_text = _read_sysfs(sys_dir / "index")
        interface_dir, usb_dir = _usb_above(sys_dir / "device")
        interface: InterfaceTriple | None = None
        if interface_dir is not None:
            parts = [
                _read_hex(interface_dir / f)
                for f in ("bInterfaceClass", "bInterfaceSubClass", "bInterfaceProtocol")
            ]
            if all(p is not None for p in parts):
                interface = (int(parts[0] or 0), int(parts[1] or 0), int(parts[2] or 0))
        nodes.append(
            DeviceNode(
                path=str(path),
                number=number,
                stable_path=by_id.get(os.path.realpath(path)),
                name=_read_sysfs(sys_dir / "name"),
                access=check_access(str(path), access),
                vid=_read_hex(usb_dir / "idVendor") if usb_dir else None,
                pid=_read_hex(usb_dir / "idProduct") if usb_dir else None,
                location=_usb_location(usb_dir) if usb_dir else None,
                interface=interface,
                index=int(index_text) if index_text and index_text.isdigit() else None,
            )
        )
    return tuple(nodes)


# -- recognition ----------------------------------------------------------------------------------------


def match_known(
    vid: int | None,
    pid: int | None,
    interfaces: Iterable[InterfaceTriple] = (),
    *,
    transports: Sequence[Transport] | None = None,
    table: Sequence[KnownDevice] = KNOWN_DEVICES,
) -> KnownDevice | None:
    """The first table row that claims this device (restricted to ``transports`` when given)."""
    interfaces = tuple(interfaces)
    for known in table:
        if transports is not None and known.transport not in transports:
            continue
        if known.match.matches(vid, pid, interfaces):
            return known
    return None


def _notes(known: KnownDevice, *, via_usb_only: bool, access: Access | None) -> tuple[str, ...]:
    notes: list[str] = []
    if access is not None and access.ok is False and access.hint:
        notes.append(f"no access: {access.hint}")
    if via_usb_only and known.transport is Transport.SERIAL:
        notes.append(f"no serial port for it: is the {known.kernel_driver} kernel driver loaded?")
    if via_usb_only and known.transport is Transport.V4L2:
        notes.append(f"no /dev/video node for it: is the {known.kernel_driver} kernel driver loaded?")
    if known.generic_id:
        notes.append(f"{known.match.describe()} is a common id, so this is a likely guess, not a certainty")
    available = BACKENDS.get(known.kind, {}) if known.kind is not None else {}
    if known.kind is not None and known.backend is not None and known.backend not in available:
        notes.append(f"this build has no '{known.backend}' {known.kind.value} backend yet")
    notes.extend(known.notes)
    return tuple(notes)


def render_config(known: KnownDevice, path: str | None, serial: str | None) -> str | None:
    """The config snippet `vlp-agent devices` prints for ``known``, with placeholders for unknown values."""
    if known.config is None:
        return None
    return known.config.format(path=path or UNKNOWN_PATH, serial=serial or UNKNOWN_SERIAL)


def _same_device(found: Recognized, location: str | None, vid: int, pid: int, serial: str | None) -> bool:
    if found.location is not None and location is not None:
        return found.location == location
    if (found.vid, found.pid) != (vid, pid):
        return False
    return found.serial_number is None or serial is None or found.serial_number == serial


def recognize(
    serial_ports: Sequence[SerialPort],
    usb_devices: Sequence[UsbDevice],
    video_devices: Sequence[DeviceNode] = (),
    *,
    table: Sequence[KnownDevice] = KNOWN_DEVICES,
) -> tuple[Recognized, ...]:
    """Name what the table knows. Kernel nodes first (they give the path the config needs), then USB
    devices that no node accounted for (cameras driven from user space, or a tty whose driver is missing)."""
    found: list[Recognized] = []
    for port in serial_ports:
        known = match_known(port.vid, port.pid, transports=(Transport.SERIAL,), table=table)
        if known is None:
            continue
        path = port.config_path
        found.append(
            Recognized(
                known,
                port.device,
                path,
                port.vid,
                port.pid,
                port.serial_number,
                port.location,
                render_config(known, path, port.serial_number),
                _notes(known, via_usb_only=False, access=port.access),
            )
        )
    for node in video_devices:
        if node.index not in (0, None) or node.interface is None:
            continue
        known = match_known(node.vid, node.pid, (node.interface,), transports=(Transport.V4L2,), table=table)
        if known is None:
            continue
        path = node.config_path
        notes = _notes(known, via_usb_only=False, access=node.access)
        found.append(
            Recognized(
                known,
                node.path,
                path,
                node.vid,
                node.pid,
                None,
                node.location,
                render_config(known, path, None),
                notes,
            )
        )
    for dev in usb_devices:
        known = match_known(dev.vid, dev.pid, dev.interfaces, table=table)
        if known is None:
            continue
        if any(
            r.known.key == known.key and _same_device(r, dev.location, dev.vid, dev.pid, dev.serial_number)
            for r in found
        ):
            continue
        where = f"USB {dev.location}" if dev.location else f"USB bus {dev.bus} device {dev.address}"
        # Only user-space USB devices need /dev/bus/usb access; tty and video devices go through their node.
        usb_access = dev.access if known.transport is Transport.USB else None
        found.append(
            Recognized(
                known,
                where,
                None,
                dev.vid,
                dev.pid,
                dev.serial_number,
                dev.location,
                render_config(known, None, dev.serial_number),
                _notes(known, via_usb_only=True, access=usb_access),
            )
        )
    return tuple(found)


def discover(
    *,
    comports: Callable[[], Iterable[Any]] | None = None,
    usb_backend: Any = None,
    dev_root: Path = Path("/dev"),
    sys_root: Path = Path("/sys"),
    access: AccessCheck = os.access,
) -> Discovery:
    """Look at everything once. Each part that fails says why in the result; none stops the others."""
    serial_error: str | None = None
    try:
        ports = list_serial_ports(comports, dev_root=dev_root, sys_root=sys_root, access=access)
    except ImportError:
        ports, serial_error = (), "pyserial is not installed: pip install pyserial"
    usb = list_usb_devices(usb_backend, dev_root=dev_root, sys_root=sys_root, access=access)
    i2c = list_i2c_buses(dev_root=dev_root, sys_root=sys_root, access=access)
    video = list_video_devices(dev_root=dev_root, sys_root=sys_root, access=access)
    usb_devices = tuple(d for d in usb.devices if not d.is_hub)
    return Discovery(ports, usb, i2c, video, recognize(ports, usb_devices, video), serial_error)
