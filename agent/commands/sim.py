"""``vlp-agent sim``: the robot on the simulated world, through the real drivers and the real bytes.

Today this is the device layer end to end (VLP, SLAM and fusion have not landed): every fake device is
served where hardware would be, the drivers open them with the same keys a robot's config uses, the world's
route is driven with Dynamixel velocity commands, and the laser, camera, IMU, wheel odometry and RFID reads
come back through their protocols. The reported pose is wheel odometry, compared with ground truth.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

import cv2
import numpy as np

from agent.commands.worlds import resolve_world
from drivers.camera.base import Camera
from drivers.errors import DeviceError
from drivers.imu.base import Imu
from drivers.laser.base import LaserScanner
from drivers.registry import DeviceKind, backend_class
from drivers.rfid.base import RfidReader
from drivers.servos.base import WheelServos
from drivers.servos.odometry import WheelOdometry
from drivers.sim.harness import SimulatedRobot
from drivers.sim.route import RouteFollower
from drivers.sim.simulation import Simulation
from drivers.sim.worldfile import load_world

log = logging.getLogger(__name__)

STAGE = "device layer only: VLP, SLAM and fusion are not built yet; the pose is wheel odometry"


def add_parser(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "sim",
        help="run the robot on the simulated world (no hardware needed)",
        description="Run the robot on a simulated world: fake laser, servos and RFID reader on "
        "pseudo-terminals, a fake IMU behind smbus2 and the simulated rolling-shutter camera, all opened "
        "through the real drivers. The world's route is driven with Dynamixel velocity commands. Prints a "
        "live status line and a summary. " + STAGE + ".",
    )
    p.add_argument("--world", metavar="FILE", help="world file (default: examples/worlds/office.toml)")
    p.add_argument("--seconds", type=float, default=20.0, help="how long to run (default: 20)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout")
    p.add_argument("--seed", type=int, default=0, help="seed for the simulated sensors' noise (default: 0)")
    p.add_argument("--trajectory", metavar="PNG", help="also draw the true and odometry paths into PNG")


@dataclass
class Counts:
    scans: int = 0
    frames: int = 0
    leds_seen: list[int] = field(default_factory=list)
    tag_reads: int = 0
    tags: set[str] = field(default_factory=set)
    imu_samples: int = 0
    errors: dict[str, int] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def error(self, device: str) -> None:
        with self.lock:
            self.errors[device] = self.errors.get(device, 0) + 1


def open_devices(config: dict[str, dict[str, Any]], simulation: Simulation, seed: int) -> dict[str, Any]:
    """Open every device from config tables, by backend name, as the agent does on a robot."""
    devices: dict[str, Any] = {}
    for kind in (DeviceKind.SERVOS, DeviceKind.LASER, DeviceKind.IMU, DeviceKind.RFID, DeviceKind.CAMERA):
        table = dict(config[kind.value])
        backend = table.pop("backend")
        cls = backend_class(kind, backend)
        if kind is DeviceKind.RFID:
            table["protocol"] = backend
        if kind is DeviceKind.CAMERA and backend == "sim":
            table = {"simulation": simulation, "seed": seed}
        device = cls(**table)
        device.open()
        devices[kind.value] = device
    return devices


def count_leds(image: np.ndarray) -> int:
    """Bright blobs in a frame (stripes bridged by a closing): a quick look, not the VLP detector."""
    _, binary = cv2.threshold(image, 60, 255, cv2.THRESH_BINARY)
    binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (9, 9)))
    n, _, stats, _ = cv2.connectedComponentsWithStats(binary)
    return int(np.count_nonzero(stats[1:, cv2.CC_STAT_AREA] >= 30)) if n > 1 else 0


def _loop(stop: threading.Event, name: str, counts: Counts, body: Callable[[], None]) -> threading.Thread:
    def run() -> None:
        while not stop.is_set():
            try:
                body()
            except DeviceError:
                counts.error(name)
                stop.wait(0.1)

    thread = threading.Thread(target=run, name=f"sim-{name}", daemon=True)
    thread.start()
    return thread


def run(args: argparse.Namespace) -> int:
    world = load_world(resolve_world(args.world))
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    live = sys.stderr.isatty() and not args.json
    counts = Counts()
    with SimulatedRobot(world, seed=args.seed) as robot:
        sim = robot.simulation
        devices = open_devices(robot.device_config(), sim, args.seed)
        servos: WheelServos = devices["servos"]
        laser: LaserScanner = devices["laser"]
        imu: Imu = devices["imu"]
        rfid: RfidReader = devices["rfid"]
        camera: Camera = devices["camera"]
        try:
            laser.start()

            def scan_once() -> None:
                laser.read(timeout_s=1.0)
                with counts.lock:
                    counts.scans += 1

            def frame_once() -> None:
                frame = camera.grab(timeout_s=1.0)
                n = count_leds(frame.image)
                with counts.lock:
                    counts.frames += 1
                    counts.leds_seen.append(n)

            def tag_once() -> None:
                tag = rfid.read(timeout_s=0.5)
                if tag is not None:
                    with counts.lock:
                        counts.tag_reads += 1
                        counts.tags.add(tag.tag_id)

            threads = [
                _loop(stop, "laser", counts, scan_once),
                _loop(stop, "camera", counts, frame_once),
                _loop(stop, "rfid", counts, tag_once),
            ]
            summary = _drive(args, world.route, world.route_speed_mps, sim, servos, imu, counts, stop, live)
        finally:
            stop.set()
            with contextlib.suppress(DeviceError):
                servos.stop()
            for device in devices.values():
                device.close()
        for thread in threads:
            thread.join(timeout=2.0)
        summary["health"] = {name: d.health().counters for name, d in devices.items()}
    summary["stage"] = STAGE
    if args.json:
        print(json.dumps(summary, sort_keys=True))
    else:
        _print_summary(summary)
    return 0


def _drive(
    args: argparse.Namespace,
    route: tuple[tuple[float, float], ...],
    speed_mps: float,
    sim: Simulation,
    servos: WheelServos,
    imu: Imu,
    counts: Counts,
    stop: threading.Event,
    live: bool,
) -> dict[str, Any]:
    robot = sim.world.robot
    start = robot.start
    follower = RouteFollower(route, speed_mps)
    odometry = WheelOdometry(robot.wheel_radius_m, robot.track_m, start.x_m, start.y_m, start.yaw_rad)
    servos.ping()
    servos.torque(True)
    period_s = 0.05
    t0 = time.monotonic()
    next_status = t0 + 1.0
    imu_yaw = start.yaw_rad
    last_imu_ns: int | None = None
    odom_errors: list[float] = []
    truth_path: list[tuple[float, float]] = []
    odom_path: list[tuple[float, float]] = []
    tick = t0
    while not stop.is_set() and time.monotonic() - t0 < args.seconds:
        try:
            state = servos.read()
            odom = odometry.update(state)
            sample = imu.read()
            counts.imu_samples += 1
            if last_imu_ns is not None:
                imu_yaw += sample.gyro_radps[2] * (sample.host_time_ns - last_imu_ns) * 1e-9
            last_imu_ns = sample.host_time_ns
            truth = sim.pose()
            # The autopilot steers from the true pose until VLP and SLAM give the agent its own.
            v, omega = follower.command(truth.x_m, truth.y_m, truth.yaw_rad)
            half = omega * robot.track_m / 2.0
            servos.set_velocity((v - half) / robot.wheel_radius_m, (v + half) / robot.wheel_radius_m)
        except DeviceError as exc:
            log.warning("drive loop: %s", exc)
            counts.error(type(exc).__name__)
            stop.wait(0.1)
            continue
        err = math.hypot(odom.x_m - truth.x_m, odom.y_m - truth.y_m)
        odom_errors.append(err)
        truth_path.append((truth.x_m, truth.y_m))
        odom_path.append((odom.x_m, odom.y_m))
        now = time.monotonic()
        if now >= next_status:
            next_status += 1.0
            el = now - t0
            leds = counts.leds_seen[-1] if counts.leds_seen else 0
            line = (
                f"t={el:5.1f}s true=({truth.x_m:6.2f},{truth.y_m:6.2f},"
                f"{math.degrees(truth.yaw_rad):6.1f}deg) "
                f"odom err={100 * err:5.1f}cm scans={counts.scans / el:4.1f}/s "
                f"frames={counts.frames / el:4.1f}/s leds={leds} imu={counts.imu_samples / el:4.0f}/s "
                f"tags={len(counts.tags)}"
            )
            if live:
                print("\r" + line, end="", file=sys.stderr, flush=True)
            elif not args.json:
                print(line, file=sys.stderr, flush=True)
        tick += period_s
        stop.wait(max(0.0, tick - time.monotonic()))
    if live:
        print(file=sys.stderr)
    elapsed = time.monotonic() - t0
    truth = sim.pose()
    final = odometry.odom
    if args.trajectory and truth_path:
        _draw(Path(args.trajectory), sim, truth_path, odom_path)
    return {
        "world": sim.world.name,
        "seconds": round(elapsed, 3),
        "distance_m": round(final.distance_m if final else 0.0, 3),
        "scans": counts.scans,
        "scan_rate_hz": round(counts.scans / elapsed, 2),
        "frames": counts.frames,
        "frame_rate_hz": round(counts.frames / elapsed, 2),
        "leds_in_view_mean": round(float(np.mean(counts.leds_seen)), 2) if counts.leds_seen else 0.0,
        "imu_samples": counts.imu_samples,
        "imu_yaw_error_deg": round(math.degrees(abs(math.remainder(imu_yaw - truth.yaw_rad, math.tau))), 3),
        "tag_reads": counts.tag_reads,
        "tags_seen": sorted(counts.tags),
        "odometry_error_m_final": round(odom_errors[-1], 4) if odom_errors else None,
        "odometry_error_m_max": round(max(odom_errors), 4) if odom_errors else None,
        "device_errors": dict(counts.errors),
    }


def _draw(
    path: Path, sim: Simulation, truth: list[tuple[float, float]], odom: list[tuple[float, float]]
) -> None:
    walls = np.array([(w.x1_m, w.y1_m, w.x2_m, w.y2_m) for w in sim.world.walls]).reshape(-1, 4)
    pts = np.array(truth + odom)
    xs = np.concatenate([walls[:, 0], walls[:, 2], pts[:, 0]])
    ys = np.concatenate([walls[:, 1], walls[:, 3], pts[:, 1]])
    scale = 800 / max(xs.max() - xs.min(), ys.max() - ys.min(), 1e-3)
    h = int((ys.max() - ys.min()) * scale) + 40
    w = int((xs.max() - xs.min()) * scale) + 40
    img = np.full((h, w, 3), 255, np.uint8)

    def px(x: float, y: float) -> tuple[int, int]:
        return int(20 + (x - xs.min()) * scale), int(h - 20 - (y - ys.min()) * scale)

    for x1, y1, x2, y2 in walls:
        cv2.line(img, px(x1, y1), px(x2, y2), (0, 0, 0), 2)
    for led in sim.world.leds:
        cv2.circle(img, px(led.x_m, led.y_m), 4, (0, 200, 255), -1)
    for line, colour in ((truth, (0, 160, 0)), (odom, (0, 0, 220))):
        cv2.polylines(img, [np.array([px(x, y) for x, y in line], np.int32)], False, colour, 2)
    cv2.putText(
        img, "green: truth  red: wheel odometry", (20, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1
    )
    tmp = path.with_name(path.name + ".tmp.png")
    cv2.imwrite(str(tmp), img)
    tmp.replace(path)


def _print_summary(s: dict[str, Any]) -> None:
    print(f"vlp-agent sim on world {s['world']!r} for {s['seconds']:.1f} s ({s['stage']})")
    print(f"  driven            {s['distance_m']:.2f} m along the route")
    print(f"  laser             {s['scans']} scans ({s['scan_rate_hz']:.1f}/s)")
    print(
        f"  camera            {s['frames']} frames ({s['frame_rate_hz']:.1f}/s), "
        f"{s['leds_in_view_mean']:.1f} LEDs in view on average"
    )
    print(
        f"  imu               {s['imu_samples']} samples, "
        f"integrated yaw off by {s['imu_yaw_error_deg']:.2f} deg"
    )
    print(f"  rfid              {s['tag_reads']} reads of {len(s['tags_seen'])} tags {s['tags_seen']}")
    print(
        f"  wheel odometry    error {100 * (s['odometry_error_m_final'] or 0):.1f} cm at the end, "
        f"{100 * (s['odometry_error_m_max'] or 0):.1f} cm at most"
    )
    errors = s["device_errors"]
    print(f"  device errors     {errors if errors else 'none'}")
