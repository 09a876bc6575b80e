"""`vlp-agent devices` on fake machines: a pyusb backend that answers like libusb, pyserial port records,
and /dev + /sys trees in a temp folder. Plus the real command on this machine, in-process and as a process."""

from __future__ import annotations

import argparse
import array
import errno
import grp
import importlib.util
import json
import os
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import usb.backend
import usb.backend.libusb1
import usb.core
import usb.libloader
from serial.tools.list_ports_common import ListPortInfo

from agent import cli
from agent.commands import devices as devices_command
from agent.config import parse_config
from drivers import discovery
from drivers.discovery import KNOWN_DEVICES, Discovery, discover, render_config
from drivers.registry import DeviceKind

REPO = Path(__file__).resolve().parents[2]

GET_DESCRIPTOR = 0x06
STRING_DESCRIPTOR = 0x03
LANGID_EN_US = 0x0409


# -- a pyusb backend for a machine that does not exist -----------------------------------------------


@dataclass
class FakeUsb:
    vid: int
    pid: int
    bus: int = 1
    address: int = 2
    ports: tuple[int, ...] = (1,)
    device_class: int = 0x00
    interfaces: list[tuple[int, int, int]] = field(default_factory=lambda: [(0xFF, 0, 0)])
    manufacturer: str | None = None
    product: str | None = None
    serial: str | None = None
    open_errno: int | None = None  # what open_device fails with (EACCES: no udev rule)
    broken_descriptor: bool = False

    def strings(self) -> dict[int, str]:
        table = {1: self.manufacturer, 2: self.product, 3: self.serial}
        return {i: s for i, s in table.items() if s is not None}


class FakeBackend(usb.backend.IBackend):  # type: ignore[misc]
    """Enough of IBackend for find(), configuration walks and string descriptors (or their failure)."""

    def __init__(self, devices: list[FakeUsb]) -> None:
        super().__init__()
        self.devices = devices
        self.open_handles = 0

    def enumerate_devices(self) -> Iterator[FakeUsb]:
        return iter(self.devices)

    def get_device_descriptor(self, dev: FakeUsb) -> SimpleNamespace:
        if dev.broken_descriptor:
            raise usb.core.USBError("Input/Output Error", -1, errno.EIO)
        strings = dev.strings()
        return SimpleNamespace(
            bLength=18,
            bDescriptorType=1,
            bcdUSB=0x0200,
            bDeviceClass=dev.device_class,
            bDeviceSubClass=0,
            bDeviceProtocol=0,
            bMaxPacketSize0=64,
            idVendor=dev.vid,
            idProduct=dev.pid,
            bcdDevice=0x0100,
            iManufacturer=1 if 1 in strings else 0,
            iProduct=2 if 2 in strings else 0,
            iSerialNumber=3 if 3 in strings else 0,
            bNumConfigurations=1,
            address=dev.address,
            bus=dev.bus,
            port_number=dev.ports[-1] if dev.ports else None,
            port_numbers=dev.ports,
            speed=3,
        )

    def get_configuration_descriptor(self, dev: FakeUsb, config: int) -> SimpleNamespace:
        if config != 0:
            raise IndexError(config)
        return SimpleNamespace(
            bLength=9,
            bDescriptorType=2,
            wTotalLength=9 + 9 * len(dev.interfaces),
            bNumInterfaces=len(dev.interfaces),
            bConfigurationValue=1,
            iConfiguration=0,
            bmAttributes=0x80,
            bMaxPower=50,
            extra_descriptors=[],
        )

    def get_interface_descriptor(self, dev: FakeUsb, intf: int, alt: int, config: int) -> SimpleNamespace:
        if config != 0 or alt != 0 or intf >= len(dev.interfaces):
            raise IndexError((intf, alt, config))
        cls, sub, proto = dev.interfaces[intf]
        return SimpleNamespace(
            bLength=9,
            bDescriptorType=4,
            bInterfaceNumber=intf,
            bAlternateSetting=0,
            bNumEndpoints=0,
            bInterfaceClass=cls,
            bInterfaceSubClass=sub,
            bInterfaceProtocol=proto,
            iInterface=0,
            extra_descriptors=[],
        )

    def open_device(self, dev: FakeUsb) -> FakeUsb:
        if dev.open_errno is not None:
            # What libusb1.py raises for LIBUSB_ERROR_ACCESS.
            raise usb.core.USBError("Access denied (insufficient permissions)", -3, dev.open_errno)
        self.open_handles += 1
        return dev

    def close_device(self, handle: FakeUsb) -> None:
        self.open_handles -= 1

    def ctrl_transfer(
        self,
        handle: FakeUsb,
        bmRequestType: int,
        bRequest: int,
        wValue: int,
        wIndex: int,
        data: Any,
        timeout: int,
    ) -> int:
        assert (bmRequestType, bRequest) == (0x80, GET_DESCRIPTOR)
        kind, index = wValue >> 8, wValue & 0xFF
        strings = handle.strings()
        if kind != STRING_DESCRIPTOR or (index and index not in strings):
            raise usb.core.USBError("Pipe error", -9, errno.EPIPE)
        if index == 0:
            payload = bytes([4, STRING_DESCRIPTOR]) + LANGID_EN_US.to_bytes(2, "little")
        else:
            assert wIndex == LANGID_EN_US
            text = strings[index].encode("utf-16-le")
            payload = bytes([2 + len(text), STRING_DESCRIPTOR]) + text
        n = min(len(payload), len(data))
        data[:n] = array.array("B", payload[:n])
        return n


def port(
    device: str,
    vid: int | None = None,
    pid: int | None = None,
    *,
    serial: str | None = None,
    location: str | None = None,
    product: str | None = None,
) -> ListPortInfo:
    """A pyserial port record as list_ports_linux fills it from sysfs."""
    info = ListPortInfo(device, skip_link_detection=True)
    if vid is not None:
        info.vid, info.pid = vid, pid
        info.serial_number, info.location, info.product = serial, location, product
        info.apply_usb_info()
    return info


@pytest.fixture
def roots(tmp_path: Path) -> tuple[Path, Path]:
    dev, sys_root = tmp_path / "dev", tmp_path / "sys"
    dev.mkdir()
    sys_root.mkdir()
    return dev, sys_root


def run_discover(
    roots: tuple[Path, Path],
    *,
    ports: list[ListPortInfo] | None = None,
    usb_devices: list[FakeUsb] | None = None,
    **kwargs: Any,
) -> Discovery:
    dev, sys_root = roots
    backend = FakeBackend(usb_devices or [])
    found = discover(
        comports=lambda: list(ports or []), usb_backend=backend, dev_root=dev, sys_root=sys_root, **kwargs
    )
    assert backend.open_handles == 0, "every device opened for its strings must be closed again"
    return found


def flat(text: str) -> str:
    """The report with its line wrapping undone, for phrase checks."""
    return " ".join(text.split())


def by_key(found: Discovery) -> dict[str, discovery.Recognized]:
    return {r.known.key: r for r in found.recognized}


# -- the table ----------------------------------------------------------------------------------------


def test_every_config_snippet_is_valid_toml() -> None:
    keys = [k.key for k in KNOWN_DEVICES]
    assert len(keys) == len(set(keys))
    for known in KNOWN_DEVICES:
        if known.config is None:
            continue
        parsed = tomllib.loads(known.config.format(path="/dev/ttyX", serial="S1"))
        if known.kind is not None and known.backend is not None:
            assert parsed[known.kind.value]["backend"] == known.backend


# -- USB through the fake backend ------------------------------------------------------------------------


def test_recognizes_the_robots_usb_devices_and_lists_the_rest_plainly(roots: tuple[Path, Path]) -> None:
    found = run_discover(
        roots,
        usb_devices=[
            FakeUsb(
                0x15D1,
                0x0000,
                address=3,
                ports=(1, 2),
                interfaces=[(0x02, 0x02, 0x01), (0x0A, 0, 0)],
                manufacturer="Hokuyo Data Flex for USB",
                product="URG-Series USB Driver",
            ),
            FakeUsb(
                0x0403, 0x6014, address=4, ports=(1, 3), product="USB <-> Serial Converter", serial="FT4NQ1"
            ),
            FakeUsb(0x0483, 0x5740, address=5, ports=(1, 4), interfaces=[(0x02, 0x02, 0x01), (0x0A, 0, 0)]),
            FakeUsb(
                0x2676,
                0xBA02,
                address=6,
                ports=(2,),
                device_class=0xEF,
                interfaces=[(0xEF, 0x05, 0x00), (0xEF, 0x05, 0x01), (0xEF, 0x05, 0x02)],
                manufacturer="Basler",
                product="acA1300-200um",
                serial="22334455",
            ),
            FakeUsb(0xF622, 0x0001, address=7, ports=(1, 5), product="MV-UB300"),
            FakeUsb(0x1234, 0x5678, address=8, ports=(1, 6), interfaces=[(0x03, 0x01, 0x02)]),
            FakeUsb(
                0x1D6B,
                0x0002,
                address=1,
                ports=(),
                device_class=0x09,
                interfaces=[(0x09, 0, 0)],
                product="EHCI Host Controller",
            ),
        ],
    )
    assert found.usb.error is None
    recognized = by_key(found)
    assert set(recognized) == {"hokuyo-urg", "robotis-u2d2", "robotis-opencr", "usb3vision", "mindvision"}

    urg = recognized["hokuyo-urg"]
    assert urg.where == "USB 1-1.2" and urg.path is None
    assert urg.config == '[laser]\nbackend = "urg"\nurl = "<port>"'
    assert any("cdc_acm" in n for n in urg.notes), "a URG without a tty points at the missing driver"

    u2d2 = recognized["robotis-u2d2"]
    assert u2d2.serial_number == "FT4NQ1"
    assert u2d2.config is not None and 'backend = "dynamixel"' in u2d2.config
    assert any("latency" in n for n in u2d2.notes)
    assert any("likely guess" in n for n in u2d2.notes), "0403:6014 is a stock FTDI id"

    camera = recognized["usb3vision"]
    assert camera.config is not None and '"22334455"' in camera.config
    assert tomllib.loads(camera.config)["camera"]["backend"] == "genicam"
    # No backend drives a MindVision camera: no snippet, and a note that says so and what to use instead.
    assert recognized["mindvision"].config is None
    assert any("no backend for the MindVision SDK" in n for n in recognized["mindvision"].notes)

    # The hub is plumbing; the unknown HID device is listed plainly.
    assert [d.vid for d in found.usb_devices] == [0x15D1, 0x0403, 0x0483, 0x2676, 0xF622, 0x1234]
    unknown = found.usb_devices[-1]
    assert unknown.interfaces == ((0x03, 0x01, 0x02),) and unknown.product is None
    report = devices_command.render(found)
    assert "Recognized (5):" in report
    assert "USB devices (6, 1 hubs not shown):" in report
    unknown_line = next(line for line in report.splitlines() if "1234:5678" in line)
    assert "HID" in unknown_line and "not recognized" in unknown_line
    assert "Hokuyo URG laser scanner  15d1:0000  at USB 1-1.2" in report
    assert "acA1300-200um" in report


def test_permission_denied_device_is_reported_with_the_fix(roots: tuple[Path, Path]) -> None:
    _, sys_root = roots
    # sysfs keeps readable copies of the strings even when the device cannot be opened.
    sys_dir = sys_root / "bus" / "usb" / "devices" / "1-4"
    sys_dir.mkdir(parents=True)
    (sys_dir / "product").write_text("MV-UB300\n")
    found = run_discover(
        roots,
        usb_devices=[
            FakeUsb(0xF622, 0x0001, address=9, ports=(4,), product="never read", open_errno=errno.EACCES),
            FakeUsb(0xABCD, 0x0001, address=10, ports=(5,), product="never read", open_errno=errno.EACCES),
        ],
    )
    camera, other = found.usb_devices
    for device in (camera, other):
        assert device.access.ok is False
        assert device.access.hint is not None
        assert device.access.hint.startswith("permission denied: needs a udev rule")
        assert "plugdev" in device.access.hint
    assert 'ATTR{idVendor}=="f622"' in (camera.access.hint or "")
    assert camera.product == "MV-UB300" and other.product is None
    mindvision = by_key(found)["mindvision"]
    assert any(n.startswith("no access: permission denied") for n in mindvision.notes)
    report = devices_command.render(found)
    assert flat(report).count("NO ACCESS: permission denied: needs a udev rule") == 2


def test_usb_node_mode_decides_access_when_dev_bus_usb_is_visible(roots: tuple[Path, Path]) -> None:
    dev, _ = roots
    node = dev / "bus" / "usb" / "001" / "011"
    node.parent.mkdir(parents=True)
    node.touch()
    checked: list[str] = []

    def deny_usb(path: str, mode: int) -> bool:
        checked.append(path)
        return "/bus/usb/" not in path

    found = run_discover(
        roots, usb_devices=[FakeUsb(0xF622, 0x0002, address=11, product="MV-UB500")], access=deny_usb
    )
    (camera,) = found.usb_devices
    assert str(node) in checked
    assert camera.access.ok is False and camera.product == "MV-UB500"


def test_a_device_without_strings_is_neither_denied_nor_named(roots: tuple[Path, Path]) -> None:
    silent = FakeUsb(0x1111, 0x2222, address=12)
    found = run_discover(roots, usb_devices=[silent])
    (device,) = found.usb_devices
    assert device.access.ok is True and device.access.hint is None
    assert (device.manufacturer, device.product, device.serial_number) == (None, None, None)


def test_enumeration_failure_keeps_what_was_listed(roots: tuple[Path, Path]) -> None:
    found = run_discover(
        roots,
        usb_devices=[
            FakeUsb(0x15D1, 0x0000, address=2, ports=(1,)),
            FakeUsb(0x9999, 0x0001, address=3, ports=(2,), broken_descriptor=True),
        ],
    )
    assert [d.vid for d in found.usb.devices] == [0x15D1]
    assert found.usb.error is not None and "stopped after 1 devices" in found.usb.error
    assert "hokuyo-urg" in by_key(found)
    assert "listing incomplete" in devices_command.render(found)


# -- serial ports ------------------------------------------------------------------------------------------


def test_serial_ports_give_the_path_and_join_with_usb(roots: tuple[Path, Path]) -> None:
    dev, _ = roots
    acm = dev / "ttyACM0"
    acm.touch()
    by_id = dev / "serial" / "by-id"
    by_id.mkdir(parents=True)
    stable = by_id / "usb-Hokuyo_Data_Flex_for_USB_URG-Series_USB_Driver-if00"
    stable.symlink_to(acm)
    found = run_discover(
        roots,
        ports=[
            port(str(acm), 0x15D1, 0x0000, location="1-1.2:1.0", product="URG-Series USB Driver"),
            port(str(dev / "ttyUSB0"), 0x0403, 0x6014, serial="FT4NQ1", location="1-1.3"),
            port(str(dev / "ttyACM1"), 0x0483, 0x5740),  # no location: joined by id instead
        ],
        usb_devices=[
            FakeUsb(0x15D1, 0x0000, ports=(1, 2), address=3),
            FakeUsb(0x0403, 0x6014, ports=(1, 3), address=4, serial="FT4NQ1"),
            FakeUsb(0x0483, 0x5740, ports=(1, 4), address=5),
        ],
        access=lambda path, mode: True,
    )
    # Each device once, named by its serial port rather than its USB address.
    assert [r.known.key for r in found.recognized] == ["hokuyo-urg", "robotis-opencr", "robotis-u2d2"]
    urg = found.recognized[0]
    assert urg.where == str(acm) and urg.location == "1-1.2"
    assert urg.config == f'[laser]\nbackend = "urg"\nurl = "{stable}"'
    assert tomllib.loads(found.recognized[1].config or "")["servos"]["baudrate"] == 1_000_000
    assert tomllib.loads(found.recognized[2].config or "")["servos"]["port"] == str(dev / "ttyUSB0")
    assert not any("kernel driver" in n for r in found.recognized for n in r.notes)
    report = devices_command.render(found)
    assert f"stable name: {stable}" in report
    assert "-> Hokuyo URG laser scanner" in report


def test_inaccessible_serial_port_says_which_group(roots: tuple[Path, Path]) -> None:
    dev, _ = roots
    tty = dev / "ttyACM0"
    tty.touch(mode=0o660)
    os.chmod(tty, 0o660)
    if os.geteuid() == 0:
        os.chown(tty, -1, 4242)  # a group we are not in, as 'dialout' is for a fresh user
    elif os.getgid() == 0:
        pytest.skip("need a non-root group to own the test node")
    gid = tty.stat().st_gid
    try:
        group = grp.getgrgid(gid).gr_name
    except KeyError:
        group = str(gid)
    found = run_discover(roots, ports=[port(str(tty), 0x15D1, 0x0000)], access=lambda path, mode: False)
    (tty_port,) = found.serial_ports
    assert tty_port.access.ok is False
    hint = tty_port.access.hint or ""
    assert f"'{group}' group" in hint and ("usermod -aG" in hint or "log out and back in" in hint)
    assert any(n.startswith("no access:") for n in found.recognized[0].notes)
    assert f"NO ACCESS: {hint}" in flat(devices_command.render(found))


def test_root_only_serial_port_needs_a_udev_rule(roots: tuple[Path, Path]) -> None:
    dev, _ = roots
    tty = dev / "ttyUSB0"
    tty.touch()
    os.chmod(tty, 0o600)
    gone = str(dev / "ttyUSB9")
    found = run_discover(roots, ports=[port(str(tty)), port(gone)], access=lambda path, mode: False)
    present, missing = found.serial_ports
    assert present.access.hint is not None and "udev rule" in present.access.hint
    assert missing.access.hint == "the device node has gone (unplugged?)"


def test_phantom_legacy_uarts_are_hidden(roots: tuple[Path, Path]) -> None:
    dev, sys_root = roots
    for name, uart_type in (("ttyS0", "4"), ("ttyS1", "0"), ("ttyS2", "0")):
        (sys_root / "class" / "tty" / name).mkdir(parents=True)
        (sys_root / "class" / "tty" / name / "type").write_text(uart_type + "\n")
    found = run_discover(roots, ports=[port(str(dev / f"ttyS{i}")) for i in range(3)])
    assert [p.device for p in found.serial_ports] == [str(dev / "ttyS0")]
    assert found.recognized == ()


# -- libusb missing ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("library", "expected"),
    [
        (None, "libusb-1.0 is not installed"),
        ("libusb-1.0.so.0", "installed but would not start"),
    ],
)
def test_without_libusb_serial_ports_are_still_recognized(
    roots: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch, library: str | None, expected: str
) -> None:
    monkeypatch.setattr(usb.backend.libusb1, "get_backend", lambda *a, **k: None)
    monkeypatch.setattr(usb.libloader, "locate_library", lambda *a, **k: library)
    dev, sys_root = roots
    found = discover(
        comports=lambda: [port("/dev/ttyACM0", 0x15D1, 0x0000)],
        dev_root=dev,
        sys_root=sys_root,
        access=lambda path, mode: True,
    )
    assert found.usb.devices == ()
    assert found.usb.error is not None and expected in found.usb.error
    assert [r.known.key for r in found.recognized] == ["hokuyo-urg"]
    report = devices_command.render(found)
    assert "USB devices: cannot list them: libusb-1.0 is" in report
    assert expected in flat(report)
    assert "/dev/ttyACM0" in report


# -- I2C and video -----------------------------------------------------------------------------------------


def test_uvc_camera_from_sysfs_and_i2c_buses(roots: tuple[Path, Path]) -> None:
    dev, sys_root = roots
    usb_dir = sys_root / "devices" / "pci0000:00" / "usb1" / "1-1"
    interface_dir = usb_dir / "1-1:1.0"
    interface_dir.mkdir(parents=True)
    for name, value in (("idVendor", "046d"), ("idProduct", "0825"), ("product", "C270 HD WEBCAM")):
        (usb_dir / name).write_text(value + "\n")
    for name, value in (
        ("bInterfaceClass", "0e"),
        ("bInterfaceSubClass", "01"),
        ("bInterfaceProtocol", "00"),
    ):
        (interface_dir / name).write_text(value + "\n")
    for number in (0, 1):
        node_dir = sys_root / "class" / "video4linux" / f"video{number}"
        node_dir.mkdir(parents=True)
        (node_dir / "name").write_text("C270 HD WEBCAM\n")
        (node_dir / "index").write_text(f"{number}\n")
        (node_dir / "device").symlink_to(interface_dir)
        (dev / f"video{number}").touch()
    (dev / "video-not-a-node").touch()
    (dev / "i2c-1").touch()
    (sys_root / "class" / "i2c-dev" / "i2c-1").mkdir(parents=True)
    (sys_root / "class" / "i2c-dev" / "i2c-1" / "name").write_text("bcm2835 (i2c@7e804000)\n")

    found = run_discover(
        roots,
        usb_devices=[
            FakeUsb(
                0x046D,
                0x0825,
                ports=(1,),
                address=2,
                device_class=0xEF,
                interfaces=[(0x0E, 0x01, 0x00), (0x0E, 0x02, 0x00), (0x01, 0x01, 0x00)],
            )
        ],
        access=lambda path, mode: True,
    )
    assert [v.path for v in found.video_devices] == [str(dev / "video0"), str(dev / "video1")]
    main_node = found.video_devices[0]
    assert (main_node.vid, main_node.pid, main_node.location) == (0x046D, 0x0825, "1-1")
    assert main_node.interface == (0x0E, 0x01, 0x00)
    (uvc,) = found.recognized  # the metadata node and the USB view are the same camera
    assert uvc.known.key == "uvc" and uvc.where == str(dev / "video0")
    assert tomllib.loads(uvc.config or "")["camera"] == {"backend": "v4l2", "device": str(dev / "video0")}
    (bus,) = found.i2c_buses
    assert (bus.path, bus.number, bus.name) == (str(dev / "i2c-1"), 1, "bcm2835 (i2c@7e804000)")
    report = devices_command.render(found)
    assert "look for the IMU with `i2cdetect -y 1`" in flat(report)
    assert "metadata node" in report


# -- the command -------------------------------------------------------------------------------------------


def test_empty_machine_says_so_plainly_and_exits_0(
    roots: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    found = run_discover(roots)
    assert found.empty and found.recognized == ()
    assert devices_command.render(found).splitlines() == [
        "No serial ports, no USB devices, no I2C buses and no video devices found.",
        "Nothing recognized: no laser, Dynamixel adapter or camera is connected.",
        "Without hardware, `vlp-agent sim` runs the agent on the simulated robot.",
    ]
    monkeypatch.setattr(devices_command, "discover", lambda: found)
    assert devices_command.run(argparse.Namespace(json=False)) == 0
    assert capsys.readouterr().out.startswith("No serial ports, no USB devices")
    assert devices_command.run(argparse.Namespace(json=True)) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["serial_ports"] == [] and data["recognized"] == [] and data["usb"]["error"] is None


def test_empty_machine_without_usb_says_why(roots: tuple[Path, Path]) -> None:
    empty = Discovery((), discovery.UsbScan(error="libusb-1.0 is not installed (x)"), (), (), ())
    first = devices_command.render(empty).splitlines()[0]
    assert first.startswith("No serial ports, no I2C buses and no video devices found, and USB devices could")


def test_json_uses_lsusb_style_ids(roots: tuple[Path, Path]) -> None:
    found = run_discover(
        roots,
        ports=[port("/dev/ttyACM0", 0x15D1, 0x0000)],
        usb_devices=[FakeUsb(0xF622, 0x0001)],
        access=lambda path, mode: True,
    )
    data = json.loads(json.dumps(found.to_dict()))
    assert data["serial_ports"][0]["vid"] == "15d1" and data["serial_ports"][0]["pid"] == "0000"
    assert data["usb"]["devices"][0]["vid"] == "f622"
    assert {r["known"]["key"] for r in data["recognized"]} == {"hokuyo-urg", "mindvision"}


def test_help_text_names_every_table_row(capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser(prog="vlp-agent")
    devices_command.add_parser(parser.add_subparsers(dest="command"))
    with pytest.raises(SystemExit) as exit_info:
        parser.parse_args(["devices", "--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    for known in KNOWN_DEVICES:
        assert known.match.describe() in text and known.name in text
    assert "--json" in text


def _machine_report_ok(text: str) -> None:
    """On any machine: either something is recognized, or the report says plainly that nothing is."""
    assert "Recognized (" in text or "Nothing recognized: no laser, Dynamixel adapter or camera" in text


def test_cli_main_on_this_machine(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Only this subcommand: its siblings in cli.COMMANDS are other people's work and may not exist yet.
    monkeypatch.setattr(cli, "COMMANDS", {"devices": "agent.commands.devices"})
    assert cli.main(["devices"]) == 0
    _machine_report_ok(capsys.readouterr().out)
    assert cli.main(["devices", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert {"serial_ports", "usb", "i2c_buses", "video_devices", "recognized"} <= set(data)


# While a sibling subcommand module is still missing, `python -m agent.cli` cannot build its parser; the
# process then runs the same main() with only this subcommand registered, so this test still checks the
# real discovery of this machine in a separate process.
_ONLY_DEVICES = (
    "import sys, agent.cli as c; c.COMMANDS = {'devices': 'agent.commands.devices'}; "
    "sys.exit(c.main(sys.argv[1:]))"
)


def _vlp_agent(*args: str) -> subprocess.CompletedProcess[str]:
    missing = [name for name in cli.COMMANDS.values() if importlib.util.find_spec(name) is None]
    entry = ["-c", _ONLY_DEVICES] if missing else ["-m", "agent.cli"]
    return subprocess.run(
        [sys.executable, *entry, *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )


def test_vlp_agent_devices_as_a_process() -> None:
    report = _vlp_agent("devices")
    assert report.returncode == 0, report.stderr
    _machine_report_ok(report.stdout)
    assert "Traceback" not in report.stderr
    as_json = _vlp_agent("devices", "--json")
    assert as_json.returncode == 0, as_json.stderr
    assert isinstance(json.loads(as_json.stdout)["serial_ports"], list)


@pytest.mark.parametrize("known", [k for k in KNOWN_DEVICES if k.config is not None], ids=lambda k: k.key)
@pytest.mark.parametrize("found", [("/dev/serial/by-id/usb-X-if00", "FT4NQ1"), (None, None)])
def test_every_config_snippet_loads_in_a_robot_config(known: Any, found: tuple[Any, Any]) -> None:
    # The snippet replaces its table in the shipped real-robot config, so a key the backend does not
    # take, a backend that does not exist or a missing required key fails here as it would on the robot.
    # Placeholders (no path or serial known) still make a config that loads, to be filled in.
    snippet = render_config(known, *found)
    assert snippet is not None
    with open(REPO / "examples" / "turtlebot3.toml", "rb") as fp:
        robot = tomllib.load(fp)
    tables = tomllib.loads(snippet)
    assert len(tables) == 1
    ((kind, table),) = tables.items()
    config = parse_config({**robot, **tables}, file=f"snippet {known.key}")
    device = config.devices[DeviceKind(kind)]
    assert device.backend == table["backend"]
    assert known.backend in (None, device.backend)
    if found[0] is not None and "{path}" in (known.config or ""):
        assert found[0] in device.options.values()


def test_the_example_robot_camera_is_one_devices_recognizes() -> None:
    with open(REPO / "examples" / "turtlebot3.toml", "rb") as fp:
        camera = tomllib.load(fp)["camera"]
    backends = {k.backend for k in KNOWN_DEVICES if k.kind is DeviceKind.CAMERA and k.config is not None}
    assert camera["backend"] in backends
    assert "cti" in camera
