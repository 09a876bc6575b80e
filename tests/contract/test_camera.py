"""The camera contract, run on every backend that can run here.

* ``sim``: the simulated camera on the reference paper's Environment 1 (always).
* ``sim-forward``: the simulated forward camera of person following (``follow_straight``; always).
* ``genicam``: harvesters + the simulated GenTL producer ``viky.cti`` from the genicam wheel (always; the
  acceptance test of the GenICam backend is ``test_genicam_viky_acceptance``).
* ``v4l2-fake``: the V4L2 backend over a stand-in for ``cv2.VideoCapture`` that behaves like a UVC driver
  (clamps values, lacks some controls): the settings logic, without a /dev/video device.
* ``hardware``: a real camera when ``VLP_TEST_CAMERA`` names a ``.cti`` producer (GenICam) or a V4L2 device
  (``/dev/video0``, ``0``); skipped otherwise.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from drivers.camera.base import Camera, CameraSettings
from drivers.camera.genicam import GenicamCamera, viky_cti_path
from drivers.camera.sim import SimCamera
from drivers.camera.sim_forward import SimForwardCamera
from drivers.camera.v4l2 import EXPOSURE_UNIT_S, V4l2Camera
from drivers.errors import (
    BackendUnavailable,
    ConfigError,
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceTimeout,
)
from drivers.registry import DeviceKind, backend_class
from drivers.sim import render_protocol
from drivers.sim.forward_render import ForwardRenderer
from drivers.sim.forward_render_worker import ForwardRenderWorker
from drivers.sim.raycast import walls_array
from drivers.sim.render_worker import RenderWorker
from drivers.sim.simulation import Simulation
from drivers.sim.world import Pose2D
from drivers.sim.worldfile import load_world

REPO = Path(__file__).resolve().parents[2]
ENV1 = REPO / "examples" / "worlds" / "env1.toml"
FOLLOW = REPO / "examples" / "worlds" / "follow_straight.toml"
VIKY = viky_cti_path()
HARDWARE = os.environ.get("VLP_TEST_CAMERA")


class FastClock:
    """Simulated time running ``rate`` times faster than the wall clock (keeps the sim tests short)."""

    def __init__(self, rate: float = 5.0) -> None:
        self.rate = rate
        self.origin = time.monotonic()

    def __call__(self) -> float:
        return self.origin + self.rate * (time.monotonic() - self.origin)


class ManualClock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


class FakeCapture:
    """Behaves like OpenCV's V4L2 capture on a UVC webcam: 640x480 or 320x240 only, exposure clamped to
    3..2047 (100 us units), frame rate 30 or 15, no gain control (get returns -1, set returns False), BGR
    frames, buffer timestamps in ms. Records every set() call."""

    MODES = ((640, 480), (320, 240))

    def __init__(self, device: int | str, api: int, opened: bool = True) -> None:
        self.device, self.api, self.opened = device, api, opened
        self.calls: list[tuple[int, float]] = []
        self.width, self.height = 640, 480
        self.pending_width: int | None = None
        self.props: dict[int, float] = {
            cv2.CAP_PROP_AUTO_EXPOSURE: 3,
            cv2.CAP_PROP_EXPOSURE: 156,
            cv2.CAP_PROP_FPS: 30.0,
            cv2.CAP_PROP_MODE: 0,
        }
        self.frames = 0
        self.fail_reads = False
        self.released = False

    def isOpened(self) -> bool:  # OpenCV's name
        return self.opened and not self.released

    def set(self, prop: int, value: float) -> bool:
        self.calls.append((prop, value))
        if prop == cv2.CAP_PROP_FRAME_WIDTH:
            self.pending_width = int(value)
            return True
        if prop == cv2.CAP_PROP_FRAME_HEIGHT:
            # Like cap_v4l: the format is renegotiated once both are set; the driver picks the nearest mode.
            want = (self.pending_width or self.width, int(value))
            self.width, self.height = min(self.MODES, key=lambda m: abs(m[0] - want[0]) + abs(m[1] - want[1]))
            return True
        if prop == cv2.CAP_PROP_EXPOSURE:
            self.props[prop] = min(max(round(value), 3), 2047)  # the driver clamps; set() still says True
            return True
        if prop == cv2.CAP_PROP_FPS:
            self.props[prop] = 30.0 if value > 22 else 15.0
            return True
        if prop in (cv2.CAP_PROP_AUTO_EXPOSURE, cv2.CAP_PROP_MODE):
            self.props[prop] = value
            return True
        return False  # e.g. CAP_PROP_GAIN: not a control of this camera

    def get(self, prop: int) -> float:
        if prop == cv2.CAP_PROP_FRAME_WIDTH:
            return float(self.width)
        if prop == cv2.CAP_PROP_FRAME_HEIGHT:
            return float(self.height)
        if prop == cv2.CAP_PROP_POS_MSEC:
            return 0.0 if self.frames == 0 else 5000.0 + self.frames * 1000.0 / self.props[cv2.CAP_PROP_FPS]
        return float(self.props.get(prop, -1.0))

    def read(self) -> tuple[bool, Any]:
        if self.fail_reads:
            return False, None
        self.frames += 1
        image = np.zeros((self.height, self.width, 3), dtype=np.uint8)
        image[:, :, 0], image[:, :, 1], image[:, :, 2] = 10, 100, 200  # B, G, R
        image[0, 0] = (self.frames % 256, 0, 0)
        return True, image

    def release(self) -> None:
        self.released = True


def make_v4l2(settings: CameraSettings | None = None, **kwargs: Any) -> tuple[V4l2Camera, list[FakeCapture]]:
    made: list[FakeCapture] = []

    def factory(device: int | str, api: int) -> FakeCapture:
        made.append(FakeCapture(device, api))
        return made[-1]

    return V4l2Camera("/dev/null", settings=settings, capture_factory=factory, **kwargs), made


def hardware_camera(settings: CameraSettings) -> Camera:
    assert HARDWARE is not None
    if HARDWARE.endswith(".cti"):
        return GenicamCamera(HARDWARE, settings=settings)
    return V4l2Camera(int(HARDWARE) if HARDWARE.isdigit() else HARDWARE, settings=settings)


BACKENDS = [
    "sim",
    "sim-forward",
    "genicam",
    "v4l2-fake",
    pytest.param(
        "hardware",
        marks=[
            pytest.mark.hardware,
            pytest.mark.skipif(HARDWARE is None, reason="set VLP_TEST_CAMERA to a .cti or a V4L2 device"),
        ],
    ),
]


@pytest.fixture(params=BACKENDS)
def make_camera(request: pytest.FixtureRequest) -> Iterator[Callable[[CameraSettings], Camera]]:
    """A factory for a fresh, unopened camera of the backend under test; cameras are closed afterwards."""
    made: list[Camera] = []

    def make(settings: CameraSettings) -> Camera:
        cam: Camera
        if request.param == "sim":
            # The real clock: the contract's "host time is not in the future" holds on it.
            cam = SimCamera(Simulation(load_world(ENV1)), settings=settings)
        elif request.param == "sim-forward":
            cam = SimForwardCamera(Simulation(load_world(FOLLOW)), settings=settings)
        elif request.param == "genicam":
            cam = GenicamCamera(VIKY, settings=settings)
        elif request.param == "v4l2-fake":
            cam = make_v4l2(settings)[0]
        else:
            cam = hardware_camera(settings)
        made.append(cam)
        return cam

    yield make
    for cam in made:
        cam.close()


CONTRACT_SETTINGS = CameraSettings(width=640, height=480, pixel_format="Mono8", frame_rate_hz=30.0)


# -- the contract --------------------------------------------------------------------------------------------
def test_frames_are_mono8_of_the_reported_size_with_rising_sequence_and_host_time(
    make_camera: Callable[[CameraSettings], Camera],
) -> None:
    with make_camera(CONTRACT_SETTINGS) as cam:
        applied = cam.settings()
        assert applied.pixel_format == "Mono8"
        assert (applied.width, applied.height) == (640, 480)
        sequences, stamps = [], []
        for _ in range(5):
            with cam.fetch(timeout_s=2.0) as frame:
                assert frame.image.dtype == np.uint8
                assert frame.image.shape == (applied.height, applied.width)
                assert frame.host_time_ns <= time.monotonic_ns()
                sequences.append(frame.sequence)
                stamps.append(frame.host_time_ns)
        assert all(b > a for a, b in itertools.pairwise(sequences))
        assert all(b > a for a, b in itertools.pairwise(stamps))
        assert cam.health().counters["frames"] == 5


def test_grab_returns_a_copy_that_outlives_the_device_buffer(
    make_camera: Callable[[CameraSettings], Camera],
) -> None:
    with make_camera(CONTRACT_SETTINGS) as cam:
        grabbed = cam.grab(timeout_s=2.0)
        kept = grabbed.image.copy()
        for _ in range(4):
            with cam.fetch(timeout_s=2.0) as frame:
                assert not np.shares_memory(frame.image, grabbed.image)
        np.testing.assert_array_equal(grabbed.image, kept)


def test_lifecycle_is_explicit_and_close_is_idempotent(
    make_camera: Callable[[CameraSettings], Camera],
) -> None:
    cam = make_camera(CONTRACT_SETTINGS)
    with pytest.raises(DeviceError), cam.fetch(timeout_s=0.5):
        pass
    cam.open()
    cam.open()  # already open: nothing happens
    assert cam.is_open and cam.health().connected
    cam.grab(timeout_s=2.0)
    cam.close()
    cam.close()
    assert not cam.is_open and not cam.health().connected
    with pytest.raises(DeviceError):
        cam.grab(timeout_s=0.5)
    with cam:  # and it opens again
        assert cam.grab(timeout_s=2.0).image.shape == (480, 640)


@pytest.mark.parametrize("backend", ["sim-forward", "v4l2-fake"])
def test_bgr8_frames_when_asked(backend: str) -> None:
    """The forward camera's format: (height, width, 3) uint8 in OpenCV's channel order."""
    settings = CameraSettings(width=640, height=480, pixel_format="BGR8")
    cam: Camera
    if backend == "sim-forward":
        cam = SimForwardCamera(Simulation(load_world(FOLLOW)), settings=settings)
    else:
        cam = make_v4l2(settings)[0]
    with cam:
        assert cam.settings().pixel_format == "BGR8"
        with cam.fetch(timeout_s=2.0) as frame:
            assert frame.image.dtype == np.uint8 and frame.image.shape == (480, 640, 3)
            assert frame.host_time_ns <= time.monotonic_ns()


# -- the GenICam backend on viky.cti -------------------------------------------------------------------------
def test_genicam_viky_acceptance(caplog: pytest.LogCaptureFixture) -> None:
    """The viky.cti producer from the genicam wheel: set width, height and Mono8, grab 20+ frames with
    timestamps, close cleanly."""
    assert os.path.isfile(VIKY), VIKY
    settings = CameraSettings(
        width=640, height=480, pixel_format="Mono8", exposure_s=1e-3, gain_db=6.0, frame_rate_hz=50.0
    )
    cam = GenicamCamera(VIKY, settings=settings)
    with caplog.at_level(logging.WARNING, logger="drivers.camera.genicam"):
        cam.open()
    try:
        applied = cam.settings()
        assert (applied.width, applied.height, applied.pixel_format) == (640, 480, "Mono8")
        assert applied.frame_rate_hz == pytest.approx(50.0)
        # viky has no ExposureTime and no Gain: logged, not fatal, and reported as absent.
        assert applied.exposure_s is None and applied.gain_db is None
        warnings = " ".join(r.getMessage() for r in caplog.records)
        assert "ExposureTime" in warnings and "Gain" in warnings
        frames = []
        for _ in range(22):
            with cam.fetch(timeout_s=2.0) as frame:
                frames.append(
                    (
                        frame.sequence,
                        frame.host_time_ns,
                        frame.device_time_ns,
                        frame.image.shape,
                        int(frame.image.max()),
                    )
                )
    finally:
        cam.close()
    assert len(frames) >= 20
    assert all(shape == (480, 640) for *_, shape, _ in frames)
    assert any(peak > 0 for *_, peak in frames)  # viky draws its balls: not an empty buffer
    sequences = [f[0] for f in frames]
    host = [f[1] for f in frames]
    assert sequences == sorted(set(sequences))
    assert all(b > a for a, b in itertools.pairwise(host)) and host[-1] <= time.monotonic_ns()
    assert all(f[2] is None for f in frames)  # viky: NotAvailableException for timestamps
    health = cam.health()
    assert not health.connected and health.counters["frames"] == 22 and health.last_error is None
    cam.close()


def test_genicam_times_out_when_no_frame_comes() -> None:
    with GenicamCamera(VIKY, settings=CameraSettings(frame_rate_hz=1.0)) as cam:
        cam.grab(timeout_s=3.0)
        with pytest.raises(DeviceTimeout):
            cam.grab(timeout_s=0.05)
        assert cam.health().counters["timeouts"] == 1


def test_genicam_picks_devices_by_serial_and_index() -> None:
    with GenicamCamera(VIKY, serial="2") as cam:
        assert cam.grab(timeout_s=2.0).image.ndim == 2
    with pytest.raises(DeviceNotFound, match="serial"):
        GenicamCamera(VIKY, serial="nope").open()
    with pytest.raises(DeviceNotFound, match="out of range"):
        GenicamCamera(VIKY, device_index=7).open()


def test_genicam_clamps_impossible_sizes_and_reports_what_it_got(caplog: pytest.LogCaptureFixture) -> None:
    with (
        caplog.at_level(logging.WARNING),
        GenicamCamera(VIKY, settings=CameraSettings(width=1000, height=50)) as cam,
    ):
        assert (cam.settings().width, cam.settings().height) == (800, 100)  # viky: 100..800
        assert cam.grab(timeout_s=2.0).image.shape == (100, 800)
    assert "Width 1000 is not possible" in caplog.text


def test_genicam_leaves_the_processs_sigint_handler_alone() -> None:
    before = signal.getsignal(signal.SIGINT)
    with GenicamCamera(VIKY):
        assert signal.getsignal(signal.SIGINT) is before


def test_genicam_missing_producer_names_the_path(tmp_path: Path) -> None:
    missing = str(tmp_path / "vendor.cti")
    with pytest.raises(DeviceNotFound, match=r"vendor\.cti") as info:
        GenicamCamera(missing).open()
    assert info.value.device == missing


def test_genicam_without_harvesters_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "harvesters.core", None)  # makes the import fail
    with pytest.raises(BackendUnavailable, match="pip install harvesters"):
        GenicamCamera(VIKY).open()


def test_registry_builds_the_backends() -> None:
    assert backend_class(DeviceKind.CAMERA, "genicam") is GenicamCamera
    assert backend_class(DeviceKind.CAMERA, "v4l2") is V4l2Camera
    assert backend_class(DeviceKind.CAMERA, "sim") is SimCamera


def test_settings_that_no_device_takes_are_config_errors() -> None:
    with pytest.raises(ConfigError, match=r"camera\.pixel_format"):
        GenicamCamera(VIKY, settings=CameraSettings(pixel_format="RGB8"))
    with pytest.raises(ConfigError, match=r"camera\.exposure_s"):
        make_v4l2(CameraSettings(exposure_s=-1.0))


# -- the V4L2 backend ----------------------------------------------------------------------------------------
def test_v4l2_device_that_is_not_there_is_not_found() -> None:
    cam = V4l2Camera("/dev/video-vlp-test-does-not-exist")
    with pytest.raises(DeviceNotFound, match="/dev/video-vlp-test-does-not-exist"):
        cam.open()
    assert not cam.is_open


def test_v4l2_settings_are_raw_v4l2_values_read_back_after_clamping(caplog: pytest.LogCaptureFixture) -> None:
    settings = CameraSettings(width=800, height=600, exposure_s=20e-6, gain_db=6.0, frame_rate_hz=20.0)
    cam, made = make_v4l2(settings, gain_raw=40)
    with caplog.at_level(logging.WARNING, logger="drivers.camera.v4l2"), cam:
        (cap,) = made
        props = [p for p, _ in cap.calls]
        # Normalisation off first, manual exposure (menu value 1) before the exposure value.
        assert cap.calls[0] == (cv2.CAP_PROP_MODE, 0)
        assert (cv2.CAP_PROP_AUTO_EXPOSURE, 1) in cap.calls
        assert props.index(cv2.CAP_PROP_AUTO_EXPOSURE) < props.index(cv2.CAP_PROP_EXPOSURE)
        assert (cv2.CAP_PROP_EXPOSURE, 1) in cap.calls  # 20 us is below one 100 us step: ask for 1
        assert (cv2.CAP_PROP_GAIN, 40) in cap.calls  # the raw gain; 6 dB cannot be mapped
        applied = cam.settings()
        # What the device really did: nearest mode, clamped exposure, nearest frame rate, no gain.
        assert (applied.width, applied.height) == (640, 480)
        assert applied.exposure_s == pytest.approx(3 * EXPOSURE_UNIT_S)
        assert applied.frame_rate_hz == 15.0
        assert applied.gain_db is None and applied.pixel_format == "Mono8"
    text = caplog.text
    assert "gain_db 6 is not applied" in text and "no V4L2_CID_GAIN" in text
    assert "asked for width 800" in text and "asked for exposure_s 2e-05" in text


def test_v4l2_frames_are_grey_with_the_buffer_timestamp() -> None:
    cam, made = make_v4l2()
    with cam:
        with cam.fetch(timeout_s=1.0) as frame:
            expected = round(0.299 * 200 + 0.587 * 100 + 0.114 * 10)
            assert frame.image.shape == (480, 640) and frame.image[5, 5] == expected
            assert frame.sequence == 1
            assert frame.device_time_ns == round((5000.0 + 1000.0 / 30.0) * 1e6)
        made[0].fail_reads = True
        with pytest.raises(DeviceTimeout):
            cam.grab(timeout_s=1.0)  # /dev/null still exists: the stream stalled
        assert cam.health().counters["timeouts"] == 1
    assert made[0].released


def test_v4l2_read_failure_with_the_device_gone_is_a_disconnect(tmp_path: Path) -> None:
    node = tmp_path / "video9"
    node.write_bytes(b"")
    made: list[FakeCapture] = []

    def factory(device: int | str, api: int) -> FakeCapture:
        made.append(FakeCapture(device, api))
        return made[-1]

    with V4l2Camera(str(node), capture_factory=factory) as cam:
        cam.grab(timeout_s=1.0)
        node.unlink()  # unplugged
        made[0].fail_reads = True
        with pytest.raises(DeviceDisconnected, match="gone"):
            cam.grab(timeout_s=1.0)


def test_v4l2_capture_that_does_not_open_is_not_found() -> None:
    cam = V4l2Camera(3, capture_factory=lambda device, api: FakeCapture(device, api, opened=False))
    with pytest.raises(DeviceNotFound, match="/dev/video3"):
        cam.open()


# -- the simulated camera ------------------------------------------------------------------------------------
def test_sim_frames_show_the_leds_the_truth_says_are_there() -> None:
    cam = SimCamera(Simulation(load_world(ENV1), clock=FastClock()), seed=3)
    with cam, cam.fetch(timeout_s=2.0) as frame:
        truth = cam.truth(frame.sequence)
        visible = [led for led in truth.leds if led.in_image]
        assert len(visible) >= 2
        for led in visible:
            u, v = (round(c) for c in led.centre_px)
            patch = frame.image[max(v - 8, 0) : v + 8, max(u - 8, 0) : u + 8]
            assert patch.max() > 100  # a lit LED where the truth puts it
        assert frame.host_time_ns == round(truth.t_mid_s * 1e9)
        assert frame.exposure_s == cam.settings().exposure_s


def test_sim_paces_frames_by_the_simulation_clock_and_counts_drops() -> None:
    clock = ManualClock()
    cam = SimCamera(Simulation(load_world(ENV1), clock=clock), start_jitter_s=0.0)
    with cam:
        period = 1.0 / cam.model.frame_rate_hz
        with pytest.raises(DeviceTimeout):
            cam.grab(timeout_s=0.05)  # the clock stands still: the first frame never finishes
        clock.t += cam.renderer.readout_s + 1e-6
        first = cam.grab(timeout_s=0.05)
        assert first.sequence == 0 and first.device_time_ns == 0
        clock.t += 3.5 * period  # the consumer fell behind by three frames
        latest = cam.grab(timeout_s=0.05)
        assert latest.sequence == 3
        assert cam.health().counters["dropped"] == 2
        assert latest.device_time_ns is not None
        assert math.isclose(latest.device_time_ns, round(3 * period * 1e9), abs_tol=1)
        assert cam.truth(3).t0_s == pytest.approx(
            clock.t - 3.5 * period - cam.renderer.readout_s - 1e-6 + 3 * period
        )


def test_sim_settings_change_what_is_rendered() -> None:
    world = load_world(ENV1)
    settings = CameraSettings(width=1280, height=960, exposure_s=40e-6, gain_db=6.0, frame_rate_hz=10.0)
    with SimCamera(Simulation(world, clock=FastClock()), settings=settings) as cam:
        applied = cam.settings()
        assert applied == CameraSettings(1280, 960, "Mono8", 40e-6, 6.0, 10.0)
        assert cam.grab(timeout_s=2.0).image.shape == (960, 1280)
        assert cam.model.led_peak_dn == pytest.approx(2 * world.camera.led_peak_dn)


def test_sim_render_process_draws_the_same_frames() -> None:
    # The renderer in a child process (what `vlp-agent sim` uses) against the one in this process: the
    # same frames pixel for pixel, and the same truth, from the same seed and clock.
    frames = {}
    for in_child in (False, True):
        clock = ManualClock()
        cam = SimCamera(
            Simulation(load_world(ENV1), clock=clock), seed=5, start_jitter_s=0.0, render_process=in_child
        )
        with cam:
            got = []
            for _ in range(3):
                clock.t += 1.0 / cam.model.frame_rate_hz + cam.renderer.readout_s
                frame = cam.grab(timeout_s=0.5)
                got.append((frame.image, cam.truth(frame.sequence)))
        frames[in_child] = got
    for (image, truth), (image_child, truth_child) in zip(frames[False], frames[True], strict=True):
        assert np.array_equal(image, image_child)
        assert truth == truth_child
    assert frames[True][0][0].max() > 100  # LEDs drawn, not an empty frame


def test_sim_render_process_that_dies_is_a_disconnect_and_reopening_starts_another() -> None:
    clock = FastClock()
    cam = SimCamera(Simulation(load_world(ENV1), clock=clock), render_process=True)
    with cam:
        cam.grab(timeout_s=2.0)
        worker = cam.renderer
        assert isinstance(worker, RenderWorker)
        worker._process.kill()
        worker._process.wait(2.0)
        with pytest.raises(DeviceDisconnected):
            cam.grab(timeout_s=2.0)
        cam.close()
        cam.open()
        assert cam.grab(timeout_s=2.0).image.max() > 100


def test_a_frame_the_render_process_answers_too_late_is_dropped_not_given_for_the_next(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A wait that ran out (a loaded machine: a child slow to start) left its answer in the pipe, and the
    next frame got it: an image of the earlier pose under the later frame's time, for every frame after."""
    world = load_world(ENV1)
    worker = RenderWorker(world.camera, world.leds, world.robot.camera_mount)
    try:
        here, there = Pose2D(0.0, 0.0, 0.0), Pose2D(0.3, -0.2, 1.0)
        monkeypatch.setattr(render_protocol, "_REPLY_TIMEOUT_S", 1e-6)  # no child answers that fast
        with pytest.raises(DeviceDisconnected, match="gave no frame"):
            worker.render(lambda t: here, 1.0)
        monkeypatch.setattr(render_protocol, "_REPLY_TIMEOUT_S", 30.0)
        frame = worker.render(lambda t: there, 2.0)
        assert frame.truth.t0_s == 2.0 and frame.truth.base_pose == there
    finally:
        worker.close()


def test_a_frame_the_forward_render_process_answers_too_late_is_dropped_not_given_for_the_next(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The forward camera's render process speaks the same protocol: a late answer is not the next frame."""
    world = load_world(FOLLOW)
    worker = ForwardRenderWorker(world.forward_camera, walls_array(world.walls))
    try:
        here, there = Pose2D(0.5, 0.0, 0.0), Pose2D(1.5, 0.2, 0.5)
        monkeypatch.setattr(render_protocol, "_REPLY_TIMEOUT_S", 1e-6)  # no child answers that fast
        with pytest.raises(DeviceDisconnected, match="gave no frame"):
            worker.render(here, [], 1.0)
        monkeypatch.setattr(render_protocol, "_REPLY_TIMEOUT_S", 30.0)
        _, truth = worker.render(there, [], 2.0)
        _, expected = ForwardRenderer(world.forward_camera, walls_array(world.walls)).render(there, [], 2.0)
        assert truth == expected and truth.t_s == 2.0
    finally:
        worker.close()
