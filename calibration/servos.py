"""Step ``servos``: find the wheel servos on the bus and set them up (ids, velocity mode, baud rate).

A servo fresh from the box answers at 57600 bps as id 1 in position mode; a spare from another robot may be
anywhere. The step broadcasts a Protocol 2.0 PING at every rate an XL430 can run (and dynamixel-sdk can set),
reads each servo's Operating Mode and Return Delay Time, then finds out which servo drives which wheel
(``--assign OLD:NEW``, or a short turn of each one while the user says which wheel moved), and writes, per
servo at its own rate, with torque off: Operating Mode 1 (velocity), Return Delay Time 0, the new id, and
the Baud Rate last (the servo answers that write at the old rate, then listens at the new one). A final
scan at the target rate checks the result. Saves the ``[servos]`` keys for the robot config.

Return Delay Time (9, 2 us units) leaves the factory at 250: each status packet waits 0.5 ms before it
goes out. 0 is what TurtleBot3 users set when the host reports "There is no status packet!" (a reply that
comes later than the host waits); it also takes 0.5 ms off every read of the agent's servo loop.

The bus is driven directly with the project's codec (``firmware_protocol.dynamixel``) over
``serial.serial_for_url``, so a scan can wait exactly as long as 253 servos would need to answer at each rate.
With ``--sim`` the bus is the fake one, with servos that listen only at their own Baud Rate register's rate.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import serial

from calibration import plot
from calibration.context import StepContext
from calibration.report import CalibrationError, Check, Console, Output, StepResult, ask_choice
from drivers.servos.control_table import BAUD_RATES, MODEL_XL430_W250, XL430_W250, ControlItem, OperatingMode
from firmware_protocol.dynamixel import (
    BROADCAST_ID,
    MAX_ID,
    DynamixelDecoder,
    StatusPacket,
    encode_ping,
    encode_read,
    encode_write,
    parse_ping_reply,
)
from firmware_protocol.errors import ProtocolError

__all__ = ["Bus", "Found", "add_arguments", "interactive", "plan_changes", "run", "scan"]

log = logging.getLogger(__name__)

NAME = "servos"
DEFAULT_FILE = "servos.toml"
# Rates an XL430 can run that dynamixel-sdk (the agent's driver) can also set: everything but 4.5 Mbps.
SCAN_RATES = (57600, 1_000_000, 115200, 2_000_000, 3_000_000, 4_000_000, 9600)
_BAUD_INDEX = {rate: index for index, rate in BAUD_RATES.items()}
_STATUS_PING_BYTES = 14
_ID = XL430_W250["ID"]
_BAUD = XL430_W250["Baud Rate"]
_MODE = XL430_W250["Operating Mode"]
_RETURN_DELAY = XL430_W250["Return Delay Time"]
_TORQUE = XL430_W250["Torque Enable"]
_GOAL_VELOCITY = XL430_W250["Goal Velocity"]
_PRESENT_POSITION = XL430_W250["Present Position"]
_MODE_NAMES = {int(m): m.name.lower().replace("_", " ") for m in OperatingMode}


# Runs a servo's short turn and says which wheel moved (someone watching; the simulation's truth).
Watcher = Callable[[Callable[[], None]], str]


@dataclass(frozen=True, slots=True)
class Found:
    id: int
    baud: int
    model: int
    firmware: int
    mode: int | None
    return_delay: int | None = None  # Return Delay Time (9), 2 us units; None: not read

    def describe(self) -> str:
        model = "XL430-W250" if self.model == MODEL_XL430_W250 else f"model {self.model}"
        mode = _MODE_NAMES.get(self.mode, str(self.mode)) if self.mode is not None else "mode unknown"
        delay = (
            f"return delay {self.return_delay * _RETURN_DELAY.scale * 1e6:g} us"
            if self.return_delay is not None
            else "return delay unknown"
        )
        return f"id {self.id} at {self.baud} bps: {model}, firmware {self.firmware}, {mode} mode, {delay}"


class Bus:
    """One Dynamixel Protocol 2.0 bus on a serial port, at a rate that can be changed. A read, or a write
    that does not move the servo, whose reply does not come within ``reply_timeout_s`` is sent again, up to
    ``RETRIES`` times."""

    RETRIES = 2

    def __init__(self, port: str, reply_timeout_s: float = 0.05) -> None:
        self.port = port
        self.reply_timeout_s = reply_timeout_s
        try:
            self._serial = serial.serial_for_url(port, baudrate=57600, timeout=0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise CalibrationError(f"cannot open the servo port {port}: {exc}") from exc
        self.baud = 57600

    def close(self) -> None:
        with contextlib.suppress(serial.SerialException, OSError):
            self._serial.close()

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def set_baud(self, baud: int) -> None:
        try:
            self._serial.baudrate = baud
        except (serial.SerialException, OSError, ValueError) as exc:
            raise CalibrationError(f"{self.port} cannot run at {baud} bps: {exc}") from exc
        self.baud = baud
        time.sleep(0.005)
        self._serial.reset_input_buffer()

    def _byte_time_s(self) -> float:
        return 10.0 / self.baud

    def _exchange(self, packet: bytes, window_s: float, expect: int | None) -> list[StatusPacket]:
        """Send ``packet`` and collect status packets for up to ``window_s`` (or until ``expect`` came)."""
        decoder = DynamixelDecoder()
        self._serial.reset_input_buffer()
        self._serial.write(packet)
        self._serial.flush()
        deadline = time.monotonic() + len(packet) * self._byte_time_s() + window_s
        replies: list[StatusPacket] = []
        while time.monotonic() < deadline:
            data = self._serial.read(4096)
            if not data:
                time.sleep(0.001)
                continue
            for p in decoder.feed(data):
                if isinstance(p, StatusPacket):
                    replies.append(p)
            if expect is not None and len(replies) >= expect:
                break
        if decoder.discarded_bytes:
            log.debug("%s at %d bps: %d bytes of noise", self.port, self.baud, decoder.discarded_bytes)
        return replies

    def ping_all(self, max_id: int = MAX_ID) -> list[tuple[int, int, int]]:
        """(id, model, firmware) of every servo answering a broadcast PING at the current rate. Waits as long
        as dynamixel-sdk does for ``max_id + 1`` servos (each answers ~3 ms after the one before)."""
        n = max_id + 1
        window = _STATUS_PING_BYTES * n * self._byte_time_s() + 0.003 * n + 0.016 + self.reply_timeout_s
        found = []
        for reply in self._exchange(encode_ping(BROADCAST_ID), window, None):
            try:
                ping = parse_ping_reply(reply)
            except ProtocolError as exc:
                log.debug("bad PING reply at %d bps: %s", self.baud, exc)
                continue
            found.append((ping.id, ping.model_number, ping.firmware_version))
        return sorted(set(found))

    def _unicast(
        self, packet: bytes, servo_id: int, what: str, also_from: int | None = None, retries: int = 0
    ) -> StatusPacket:
        """Send one instruction and return its status packet; sent again up to ``retries`` times while no
        reply comes (a reply lost to noise on a half-duplex bus, or late on a busy host)."""
        ids = {servo_id} if also_from is None else {servo_id, also_from}
        for attempt in range(retries + 1):
            replies = [r for r in self._exchange(packet, self.reply_timeout_s, 1) if r.id in ids]
            if replies:
                break
            if attempt < retries:
                log.info("servo %d: no reply to %s at %d bps; asking again", servo_id, what, self.baud)
        if not replies:
            tries = f" ({retries + 1} tries)" if retries else ""
            raise CalibrationError(f"servo {servo_id} did not answer {what} at {self.baud} bps{tries}")
        status = replies[0].status
        if status.failed:
            raise CalibrationError(f"servo {servo_id} refused {what}: {status.describe()}")
        return replies[0]

    def read(self, servo_id: int, item: ControlItem) -> int:
        packet = encode_read(servo_id, item.address, item.size)
        reply = self._unicast(packet, servo_id, f"READ {item.name}", retries=self.RETRIES)
        if len(reply.params) != item.size:
            raise CalibrationError(f"servo {servo_id}: READ {item.name} gave {len(reply.params)} bytes")
        return item.decode(reply.params)

    def write(self, servo_id: int, item: ControlItem, value: int) -> None:
        # A servo answers a write to its ID register from its new id. Writing the same value again is
        # harmless, except to ID and Baud Rate: once either has taken, the servo no longer listens where
        # the write is sent again, so those are sent once (the step, run again, scans afresh).
        new_id = value if item is _ID else None
        retries = 0 if item is _ID or item is _BAUD else self.RETRIES
        self._unicast(
            encode_write(servo_id, item.address, item.encode(value)),
            servo_id,
            f"WRITE {item.name}",
            new_id,
            retries,
        )


def scan(
    bus: Bus,
    rates: tuple[int, ...] = SCAN_RATES,
    max_id: int = MAX_ID,
    progress: Callable[[str], None] | None = None,
) -> list[Found]:
    """Every servo on the bus at any of ``rates``, with its Operating Mode and Return Delay Time."""
    found: list[Found] = []
    for rate in rates:
        if progress is not None:
            progress(f"scanning at {rate} bps ... {len(found)} servo(s) so far")
        bus.set_baud(rate)
        for servo_id, model, firmware in bus.ping_all(max_id):
            try:
                mode: int | None = bus.read(servo_id, _MODE)
            except CalibrationError as exc:
                log.warning("servo %d at %d bps: %s", servo_id, rate, exc)
                mode = None
            try:
                delay: int | None = bus.read(servo_id, _RETURN_DELAY)
            except CalibrationError as exc:
                log.warning("servo %d at %d bps: %s", servo_id, rate, exc)
                delay = None
            found.append(Found(servo_id, rate, model, firmware, mode, delay))
    return found


@dataclass
class Plan:
    """What to write to each servo (found at ``servo.baud``): the mode, the return delay, its new id and the
    rate."""

    servo: Found
    new_id: int
    wheel: str
    writes: list[tuple[ControlItem, int]] = field(default_factory=list)


def plan_changes(
    found: list[Found], wheels: dict[int, str], left_id: int, right_id: int, baud: int
) -> list[Plan]:
    """The writes that make ``wheels`` (found id -> "left"/"right") the left and right servos at ``baud``
    in velocity mode with no return delay. Raises CalibrationError when it cannot be done safely."""
    if baud not in _BAUD_INDEX:
        raise CalibrationError(
            f"an XL430 cannot run at {baud} bps; choose one of {sorted(_BAUD_INDEX.values())}"
        )
    if left_id == right_id:
        raise CalibrationError(f"left and right need different ids, both are {left_id}")
    by_id: dict[int, list[Found]] = {}
    for f in found:
        by_id.setdefault(f.id, []).append(f)
    sides = sorted(wheels.values())
    if sides != ["left", "right"]:
        raise CalibrationError(f"need exactly one left and one right wheel servo, got {wheels}")
    plans = []
    for servo_id, wheel in wheels.items():
        entries = by_id.get(servo_id)
        if not entries:
            raise CalibrationError(f"servo {servo_id} was not found on the bus")
        if len(entries) > 1:
            raise CalibrationError(
                f"id {servo_id} answers at {[e.baud for e in entries]} bps: two servos share it; connect one "
                "at "
                "a time to tell them apart"
            )
        servo = entries[0]
        new_id = left_id if wheel == "left" else right_id
        plan = Plan(servo, new_id, wheel)
        if servo.mode != OperatingMode.VELOCITY:
            plan.writes.append((_MODE, int(OperatingMode.VELOCITY)))
        if servo.return_delay != 0:
            plan.writes.append((_RETURN_DELAY, 0))
        if new_id != servo.id:
            plan.writes.append((_ID, new_id))
        if servo.baud != baud:
            plan.writes.append((_BAUD, _BAUD_INDEX[baud]))
        plans.append(plan)
    chosen = {p.servo.id for p in plans}
    for other in found:
        if other.id not in chosen and other.id in (left_id, right_id):
            raise CalibrationError(
                f"another servo ({other.describe()}) already has id {other.id}: it would clash with the "
                f"{'left' if other.id == left_id else 'right'} wheel; disconnect it or give it another id "
                "first"
            )
    return plans


def apply(bus: Bus, plans: list[Plan], say: Callable[[str], None]) -> None:
    """Torque off, then the planned writes (Baud Rate last, since it moves the servo), servo by servo.
    On a failure the error says what was already written; running the step again scans afresh and finishes."""
    done: list[str] = []
    for plan in plans:
        servo = plan.servo
        if not plan.writes:
            say(f"  {plan.wheel} wheel: id {servo.id} already set")
            continue
        bus.set_baud(servo.baud)
        servo_id = servo.id
        try:
            bus.write(servo_id, _TORQUE, 0)
            for item, value in plan.writes:
                bus.write(servo_id, item, value)
                if item is _ID:
                    servo_id = value
                done.append(f"{plan.wheel} {item.name} = {value}")
                say(f"  {plan.wheel} wheel: wrote {item.name} = {value} (servo now id {servo_id})")
        except CalibrationError as exc:
            written = "; already written to the servos: " + ", ".join(done) if done else ""
            raise CalibrationError(
                f"{exc}{written}. Run the step again: it scans afresh and finishes the job"
            ) from exc


def wiggle(bus: Bus, servo: Found, seconds: float = 0.4) -> None:
    """Turn one servo slowly for a moment (velocity mode, then back to torque off)."""
    bus.set_baud(servo.baud)
    bus.write(servo.id, _TORQUE, 0)
    if servo.mode != OperatingMode.VELOCITY:
        bus.write(servo.id, _MODE, int(OperatingMode.VELOCITY))
    bus.write(servo.id, _TORQUE, 1)
    try:
        bus.write(servo.id, _GOAL_VELOCITY, 60)
        time.sleep(seconds)
    finally:
        with contextlib.suppress(CalibrationError):
            bus.write(servo.id, _GOAL_VELOCITY, 0)
            bus.write(servo.id, _TORQUE, 0)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--port", help="the servo bus (default: the robot config's [servos] port)")
    p.add_argument("--baud", type=int, default=None, help="rate to set (default: the config's, else 1000000)")
    p.add_argument(
        "--left-id", type=int, default=None, help="id for the left wheel (default: config's, else 1)"
    )
    p.add_argument(
        "--right-id", type=int, default=None, help="id for the right wheel (default: config's, else 2)"
    )
    p.add_argument(
        "--assign",
        action="append",
        default=[],
        metavar="OLD:WHEEL",
        help="which found servo is which wheel, e.g. 3:right (repeat for both); without it each servo is "
        "turned "
        "briefly and you say which wheel moved",
    )
    p.add_argument(
        "--max-id", type=int, default=MAX_ID, help=f"highest id to wait for in a scan (default {MAX_ID})"
    )
    p.add_argument("--scan-only", action="store_true", help="only list the servos; change nothing")
    p.add_argument(
        "--reply-timeout-ms",
        type=float,
        default=None,
        help="how long to wait for a servo's reply (default 50 ms; 250 ms on the simulated bus, which shares "
        "the computer with everything else)",
    )


def interactive(ctx: StepContext, options: argparse.Namespace) -> argparse.Namespace:
    return options


def _parse_assign(items: list[str]) -> dict[int, str]:
    wheels: dict[int, str] = {}
    for item in items:
        old, _, wheel = item.partition(":")
        wheel = wheel.strip().lower()
        try:
            servo_id = int(old)
        except ValueError:
            raise CalibrationError(f"--assign takes OLD_ID:left or OLD_ID:right, not {item!r}") from None
        if wheel not in ("left", "right"):
            raise CalibrationError(f"--assign takes OLD_ID:left or OLD_ID:right, not {item!r}")
        wheels[servo_id] = wheel
    return wheels


@contextlib.contextmanager
def _sim_bus(ctx: StepContext) -> Iterator[tuple[str, Watcher, dict[str, int]]]:
    """The simulated robot's servo bus, as a new robot's might be: the left servo fresh from the box (id 1,
    57600 bps, position mode), the right one a spare from another robot (id 3, 1 Mbps, extended position).
    Yields the port, a function telling which wheel a servo turned (the simulation's truth, as someone
    watching would), and the world's left/right ids."""
    from drivers.fakes.dynamixel import BaudAwareDynamixelBus
    from drivers.fakes.pty import PtyServer
    from drivers.sim.simulation import Simulation

    assert ctx.sim is not None
    world = ctx.sim.load()
    sim = Simulation(world, seed=ctx.sim.seed)
    fake = BaudAwareDynamixelBus(sim)
    left, right = world.robot.left_id, world.robot.right_id
    spare = next(i for i in range(3, 250) if i not in (left, right))
    fake.set_servo(
        left,
        new_id=1 if right != 1 else spare + 1,
        baud_index=_BAUD_INDEX[57600],
        mode=int(OperatingMode.POSITION),
    )
    fake.set_servo(
        right, new_id=spare, baud_index=_BAUD_INDEX[1_000_000], mode=int(OperatingMode.EXTENDED_POSITION)
    )
    server = PtyServer(fake)
    server.start()
    fake.attach(server.path)

    def which_wheel(turn: Callable[[], None]) -> str:
        before = sim.wheels().position_rad
        turn()
        after = sim.wheels().position_rad
        moved = [abs(a - b) for a, b in zip(after, before, strict=True)]
        return "left" if moved[0] > moved[1] else "right"

    try:
        yield server.path, which_wheel, {"left_id": left, "right_id": right}
    finally:
        server.close()
        fake.close()


def run(ctx: StepContext, options: argparse.Namespace) -> StepResult:
    console = ctx.console
    output = ctx.output(options.output, DEFAULT_FILE)
    with contextlib.ExitStack() as stack:
        if ctx.sim is not None:
            port, sim_wheel, ids = stack.enter_context(_sim_bus(ctx))
            defaults: dict[str, Any] = {"baudrate": 1_000_000, **ids}
            watcher: Watcher | None = sim_wheel
        else:
            ctx.require_robot("the servo step")
            defaults = _config_servos(ctx)
            port = str(options.port or defaults.get("port") or "")
            if not port:
                raise CalibrationError("no servo port: pass --port or give [servos] port in the config")
            watcher = None
        baud = options.baud or int(defaults.get("baudrate", 1_000_000))
        left_id = options.left_id if options.left_id is not None else int(defaults.get("left_id", 1))
        right_id = options.right_id if options.right_id is not None else int(defaults.get("right_id", 2))
        timeout_ms = options.reply_timeout_ms or (250.0 if ctx.sim is not None else 50.0)
        bus = stack.enter_context(Bus(str(port), reply_timeout_s=timeout_ms / 1000.0))
        console.say(f"servos: scanning {port} at {', '.join(str(r) for r in SCAN_RATES)} bps")
        before = scan(bus, SCAN_RATES, options.max_id, console.status)
        console.status("")
        if not before:
            raise CalibrationError(
                f"no servo answered on {port} at any rate: check the power (the servos need 12 V, not just "
                "USB), "
                "the cable, and that the adapter is in TTL mode"
            )
        for f in before:
            console.say(f"  found {f.describe()}")
        if options.scan_only:
            return _result(before, before, [], baud, left_id, right_id, output, scan_only=True)
        wheels = _parse_assign(options.assign)
        if not wheels:
            wheels = _identify(
                bus, before, console, watcher if ctx.sim is not None else None, ctx.interactive
            )
        plans = plan_changes(before, wheels, left_id, right_id, baud)
        console.say(f"servos: setting left = id {left_id}, right = id {right_id}, velocity mode, {baud} bps")
        apply(bus, plans, console.say)
        bus.set_baud(baud)
        after = [f for f in scan(bus, (baud,), options.max_id) if f.baud == baud]
        return _result(before, after, plans, baud, left_id, right_id, output, scan_only=False)
    raise AssertionError("unreachable")


def _config_servos(ctx: StepContext) -> dict[str, Any]:
    from agent.config import load_config
    from drivers.registry import DeviceKind

    assert ctx.config is not None
    config = load_config(ctx.config)
    device = config.devices.get(DeviceKind.SERVOS)
    if device is None:
        raise CalibrationError(f"{ctx.config} has no [servos] table")
    return dict(device.options)


def _identify(
    bus: Bus, found: list[Found], console: Console, watcher: Watcher | None, interactive: bool
) -> dict[int, str]:
    """Which wheel each servo drives: turn it briefly; the user (or, simulated, the simulation) says."""
    if len(found) != 2:
        raise CalibrationError(
            f"found {len(found)} servos; a two-wheel base has 2. Connect only the wheel servos, or say which "
            "is "
            "which with --assign OLD_ID:left --assign OLD_ID:right"
        )
    if watcher is None and not interactive:
        raise CalibrationError(
            "say which servo drives which wheel: --assign OLD_ID:left --assign OLD_ID:right"
        )
    wheels: dict[int, str] = {}
    for servo in found:
        console.say(
            f"  turning servo {servo.id} slowly for a moment: watch the wheels (lift the robot first)"
        )

        def turn(servo: Found = servo) -> None:
            wiggle(bus, servo)

        if watcher is not None:
            wheel = watcher(turn)
            console.say(f"  servo {servo.id} turned the {wheel} wheel")
        else:
            turn()
            wheel = ask_choice(console, f"which wheel did servo {servo.id} turn", ["left", "right"], "left")
        wheels[servo.id] = wheel
    return wheels


def _found_values(f: Found) -> dict[str, Any]:
    return {"id": f.id, "baud": f.baud, "model": f.model, "mode": f.mode, "return_delay": f.return_delay}


def _result(
    before: list[Found],
    after: list[Found],
    plans: list[Plan],
    baud: int,
    left_id: int,
    right_id: int,
    output: Any,
    *,
    scan_only: bool,
) -> StepResult:
    ids_after = {f.id: f for f in after}
    values: dict[str, Any] = {
        "found": [_found_values(f) for f in before],
        "after": [_found_values(f) for f in after],
        "baudrate": baud,
        "left_id": left_id,
        "right_id": right_id,
        "changes": [
            {"old_id": p.servo.id, "wheel": p.wheel, "writes": {i.name: v for i, v in p.writes}}
            for p in plans
        ],
    }
    report = [f"before: {f.describe()}" for f in before]
    report += [f"after:  {f.describe()}" for f in after] if not scan_only else []
    checks: list[Check] = []
    outputs: list[Output] = []
    if not scan_only:
        answering = sum(1 for i in (left_id, right_id) if i in ids_after)
        velocity = sum(
            1 for i in (left_id, right_id) if i in ids_after and ids_after[i].mode == OperatingMode.VELOCITY
        )
        no_delay = sum(1 for i in (left_id, right_id) if i in ids_after and ids_after[i].return_delay == 0)
        checks = [
            Check(f"wheel servos answering at {baud} bps", float(answering), 2.0, "of 2", at_least=True),
            Check("wheel servos in velocity mode", float(velocity), 2.0, "of 2", at_least=True),
            Check("wheel servos with Return Delay Time 0", float(no_delay), 2.0, "of 2", at_least=True),
        ]
        text = (
            "# vlp-agent calibrate servos: the [servos] keys for the robot config (docs/config.md)\n"
            + "".join(f"# found {f.describe()}\n" for f in before)
            + f"\n[servos]\nbaudrate = {baud}\nleft_id = {left_id}\nright_id = {right_id}\n"
        )
        outputs.append(Output(output, text))
    rows = [
        f"{'before' if n < len(before) else 'after'}: {f.describe()}" for n, f in enumerate(before + after)
    ]
    figure = plot.text_panel(rows or ["no servos"], title="servo bus")
    outputs.append(Output(output.with_suffix(".png"), plot.png(figure), report=True))
    advice = []
    if not scan_only:
        advice.append(
            f"copy the [servos] keys from {output} into the robot config (baudrate, left_id, right_id)"
        )
        advice.append("next: `vlp-agent calibrate wheels` (wheel radius and track)")
    return StepResult(NAME, values, checks, report, advice, outputs)
