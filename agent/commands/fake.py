"""``vlp-agent fake DEVICE``: serve one fake device on a pseudo-terminal for third-party tools.

The first line of output is the path to open (nothing else is printed before it, so a script can read it
with ``head -1``); the fake then serves until interrupted. The fake draws its data from the simulated world:
the laser ray-casts the floor plan, the servos drive the simulated robot's wheels, the RFID reader sees the
tags of the people walking by.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from agent.commands.worlds import resolve_world
from agent.runtime.shutdown import ShutdownRequest
from drivers.errors import ConfigError
from drivers.fakes.pty import ByteDevice, PtyServer, check_link_path
from drivers.sim.simulation import Simulation
from drivers.sim.worldfile import load_world

DEVICES = {
    "urg": "Hokuyo URG-04LX laser scanner, SCIP 2.0 (real PP values, MD scans every 100 ms)",
    "dynamixel": "two XL430-W250 wheel servos (ids from the world, 1 and 2 by default), Protocol 2.0",
    "rfid": "RFID reader (protocol from the world's [rfid] table: id12la, rdm6300 or mercury)",
}


def add_parser(sub: Any, argv: Sequence[str] = ()) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "fake",
        help="serve one fake device on a pseudo-terminal",
        description="Serve one fake device on a pseudo-terminal and print the path to open on the first line "
        "of output; serve until Ctrl-C or SIGTERM. Point any client at it: our drivers, dynamixel-sdk, "
        "urg_c, "
        "a terminal program. Devices: " + "; ".join(f"{k}: {v}" for k, v in DEVICES.items()) + ".",
    )
    p.add_argument("device", choices=sorted(DEVICES), help="which device to fake")
    p.add_argument("--world", metavar="FILE", help="world file (default: examples/worlds/office.toml)")
    p.add_argument(
        "--link",
        metavar="PATH",
        help="also keep a symlink at PATH pointing at the pty, like a udev rule's stable name; PATH must "
        "not exist (a dangling link into /dev/pts left by a killed fake is replaced), its folder must",
    )
    p.add_argument(
        "--rfid-protocol", choices=["id12la", "rdm6300", "mercury"], help="override the world's RFID protocol"
    )


def make_device(name: str, simulation: Simulation, rfid_protocol: str | None = None) -> ByteDevice:
    if name == "urg":
        from drivers.fakes.urg import FakeUrg

        return FakeUrg(simulation)
    if name == "dynamixel":
        from drivers.fakes.dynamixel import FakeDynamixelBus

        return FakeDynamixelBus(simulation)
    if name == "rfid":
        from drivers.fakes.rfid import FakeRfidReader

        return FakeRfidReader(simulation, rfid_protocol)
    raise ValueError(f"unknown fake device {name!r}")


def run(args: argparse.Namespace) -> int:
    if args.link is not None:
        # A usage error, like a bad argument: checked before anything starts, exit code 2.
        try:
            check_link_path(Path(args.link))
        except ConfigError as exc:
            print(f"vlp-agent fake: --link {exc.file}: {exc.reason}", file=sys.stderr)
            return 2
    world = load_world(resolve_world(args.world))
    simulation = Simulation(world)
    device = make_device(args.device, simulation, args.rfid_protocol)
    with ShutdownRequest() as shutdown, PtyServer(device, link=args.link) as server:
        print(server.path, flush=True)
        # The RFID fake's protocol is chosen from the world or --rfid-protocol: name that one, not the
        # list of choices from the help text.
        protocol = getattr(device, "protocol", None)
        what = f"RFID reader, protocol {protocol}" if protocol else DEVICES[args.device]
        print(
            f"serving a fake {args.device} ({what}) over world {world.name!r}; Ctrl-C to stop",
            file=sys.stderr,
            flush=True,
        )
        while not shutdown.requested:
            # Keep the world moving even when nobody reads it, so scans and tags stay current.
            simulation.advance()
            shutdown.wait(0.05)
    return 0
