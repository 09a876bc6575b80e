"""``vlp-agent devices``: what hardware is plugged in, which of it is the robot's, and the config to use it.

The looking is done by :mod:`drivers.discovery`; this module only words the answer for a person (or prints
it as JSON for a script). It always exits 0 when it could look: an empty machine, a missing libusb or a
denied device are findings to report, not failures.
"""

from __future__ import annotations

import argparse
import textwrap
from collections.abc import Sequence

from agent.commands.args import dumps_json
from drivers.discovery import (
    KNOWN_DEVICES,
    Access,
    DeviceNode,
    Discovery,
    Recognized,
    SerialPort,
    UsbDevice,
    discover,
)

# Names for USB class codes, for devices nobody recognized: "HID" says more than a bare id.
_USB_CLASSES = {
    0x01: "audio",
    0x02: "communications, CDC",
    0x03: "HID: keyboard, mouse, ...",
    0x07: "printer",
    0x08: "mass storage",
    0x0A: "CDC data",
    0x0B: "smart card",
    0x0E: "video",
    0x10: "audio/video",
    0xE0: "wireless: Bluetooth, ...",
    0xFF: "vendor-specific",
}
_WIDTH = 100


def _recognized_ids() -> str:
    lines = ["recognized devices (USB id, or interface class/subclass/protocol):"]
    for known in KNOWN_DEVICES:
        use = (
            f"{known.kind.value}, backend {known.backend!r}" if known.kind and known.backend else "no backend"
        )
        lines.append(f"  {known.match.describe():<15} {known.name} ({use})")
    return "\n".join(lines)


def add_parser(
    subparsers: argparse._SubParsersAction[argparse.ArgumentParser], argv: Sequence[str] = ()
) -> None:
    parser = subparsers.add_parser(
        "devices",
        help="list serial ports, USB devices, I2C buses and cameras, and name the robot's hardware",
        description=textwrap.fill(
            "List serial ports (with USB id, serial number and whether you may open them), USB devices "
            "(through pyusb/libusb), I2C buses (/dev/i2c-*) and video devices (/dev/video*). Devices the "
            "agent knows are named, with the config snippet that selects their backend. Serial ports are "
            "not opened and nothing is sent to a device beyond the standard USB string-descriptor "
            "requests, so it is safe to run while the agent is running.",
            _WIDTH,
        ),
        epilog=_recognized_ids()
        + "\n\n"
        + textwrap.fill(
            "Without libusb the USB list is skipped, but the laser and servo adapters are still recognized "
            "from their serial ports. Exit status 0 whenever the machine could be looked at, even if "
            "nothing was found.",
            _WIDTH,
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--json", action="store_true", help="print the findings as JSON, for scripts")


def run(args: argparse.Namespace) -> int:
    found = discover()
    if args.json:
        print(dumps_json(found.to_dict(), indent=2))
    else:
        print(render(found))
    return 0


# -- the report -----------------------------------------------------------------------------------------


def _usb_id(vid: int | None, pid: int | None) -> str | None:
    return f"{vid:04x}:{pid:04x}" if vid is not None and pid is not None else None


def _access_text(access: Access) -> str:
    if access.ok is False:
        return f"NO ACCESS: {access.hint}" if access.hint else "NO ACCESS"
    return ""


def _join(*parts: str | None) -> str:
    return "  ".join(p for p in parts if p)


def _wrap(text: str, indent: str) -> list[str]:
    return textwrap.wrap(
        text, _WIDTH, initial_indent=indent, subsequent_indent=indent + "  ", break_on_hyphens=False
    )


def _recognized_lines(found: Recognized) -> list[str]:
    known = found.known
    lines = [f"  {_join(known.name, _usb_id(found.vid, found.pid), 'at ' + found.where)}"]
    lines += _wrap(known.detail, "    ")
    if found.config:
        lines.append("    config:")
        lines += [f"      {line}" for line in found.config.splitlines()]
    for note in found.notes:
        lines += _wrap(f"note: {note}", "    ")
    return lines


def _serial_line(port: SerialPort) -> list[str]:
    ident = _usb_id(port.vid, port.pid) or "no USB id (built-in UART or similar)"
    name = _join(port.manufacturer, port.product) or port.description
    serial = f"serial {port.serial_number}" if port.serial_number else None
    lines = _wrap(_join(port.device, ident, name, serial, _access_text(port.access)), "  ")
    if port.stable_path:
        lines.append(f"    stable name: {port.stable_path}")
    return lines


def _usb_label(dev: UsbDevice) -> str:
    name = _join(dev.manufacturer, dev.product)
    if name:
        return name
    classes = [dev.device_class] if dev.device_class not in (0x00, 0xEF) else []
    classes += [c for c, _, _ in dev.interfaces]
    for code in classes:
        if code in _USB_CLASSES:
            return f"({_USB_CLASSES[code]})"
    return "(no name)"


def _usb_line(dev: UsbDevice, recognized: tuple[Recognized, ...]) -> list[str]:
    where = dev.location or f"bus {dev.bus} dev {dev.address}"
    known = next(
        (
            r.known.name
            for r in recognized
            if (r.location and r.location == dev.location)
            or (r.location is None and (r.vid, r.pid) == (dev.vid, dev.pid))
        ),
        None,
    )
    tag = f"-> {known}" if known else "not recognized"
    serial = f"serial {dev.serial_number}" if dev.serial_number else None
    return _wrap(
        _join(where, _usb_id(dev.vid, dev.pid), _usb_label(dev), serial, tag, _access_text(dev.access)), "  "
    )


def _node_line(node: DeviceNode) -> list[str]:
    ident = _usb_id(node.vid, node.pid)
    extra = "metadata node" if node.index not in (0, None) else None
    return _wrap(_join(node.path, node.name, ident, extra, _access_text(node.access)), "  ")


def _nothing_found(found: Discovery) -> str:
    if found.usb.error:
        return (
            f"No serial ports, no I2C buses and no video devices found, and USB devices could not be "
            f"listed: {found.usb.error}."
        )
    return "No serial ports, no USB devices, no I2C buses and no video devices found."


_NOTHING_RECOGNIZED = [
    "Nothing recognized: no laser, Dynamixel adapter or camera is connected.",
    "Without hardware, `vlp-agent sim` runs the agent on the simulated robot.",
]


def render(found: Discovery) -> str:
    """The human report: recognized devices first (what the user came for), then everything seen."""
    lines: list[str] = []
    if found.empty:
        lines += _wrap(_nothing_found(found), "")
        if found.serial_error:
            lines += _wrap(f"Serial ports could not be listed: {found.serial_error}.", "")
        lines += _NOTHING_RECOGNIZED
        return "\n".join(lines)

    if found.recognized:
        lines.append(f"Recognized ({len(found.recognized)}):")
        for item in found.recognized:
            lines += _recognized_lines(item)
    else:
        lines += _NOTHING_RECOGNIZED

    lines.append("")
    if found.serial_error:
        lines += _wrap(f"Serial ports: could not list them: {found.serial_error}", "")
    elif found.serial_ports:
        lines.append(f"Serial ports ({len(found.serial_ports)}):")
        for port in found.serial_ports:
            lines += _serial_line(port)
    else:
        lines.append("Serial ports: none")

    usb = found.usb_devices
    hubs = len(found.usb.devices) - len(usb)
    if usb:
        lines.append(f"USB devices ({len(usb)}{f', {hubs} hubs not shown' if hubs else ''}):")
        for dev in usb:
            lines += _usb_line(dev, found.recognized)
    elif not found.usb.error:
        lines.append("USB devices: none" + (f" ({hubs} hubs)" if hubs else ""))
    if found.usb.error:
        lines += _wrap(
            f"USB devices: {'listing incomplete' if usb else 'cannot list them'}: {found.usb.error}. Serial "
            "ports, I2C buses and video devices are still listed, and the laser and servo adapters are "
            "recognized from their serial ports.",
            "",
        )

    if found.i2c_buses:
        lines.append(f"I2C buses ({len(found.i2c_buses)}):")
        for bus in found.i2c_buses:
            lines += _node_line(bus)
        numbers = [str(b.number) for b in found.i2c_buses]
        command = (
            f"i2cdetect -y {numbers[0]}"
            if len(numbers) == 1
            else f"i2cdetect -y N (N = {', '.join(numbers)})"
        )
        lines += _wrap(
            f"(buses are not probed; look for the IMU with `{command}`: MPU-6050 answers at 0x68/0x69, "
            "BNO055 at 0x28/0x29)",
            "  ",
        )
    else:
        lines.append("I2C buses: none")

    if found.video_devices:
        lines.append(f"Video devices ({len(found.video_devices)}):")
        for node in found.video_devices:
            lines += _node_line(node)
    else:
        lines.append("Video devices: none")
    return "\n".join(lines)
