"""What a robot on a simulated world is told about it, as the agent's VLP types.

A real robot knows its camera from its calibration and its LEDs from their survey, both a little off the
truth. On a simulated world that knowledge is the world's nominal camera (``drivers.sim.worldfile
.nominal_camera``: the principal point before the world's principal-point error) and its surveyed LED map
(``surveyed_leds``: the LEDs moved by the world's survey error); the camera mount is the nominal one (no
tilt error). The runtime, the evaluations and the calibration wizard all build their view here.
"""

from __future__ import annotations

from dataclasses import dataclass

from agent.vlp.model import CameraIntrinsics, CameraMount, LedMap, MapLed
from drivers.sim.world import World
from drivers.sim.worldfile import nominal_camera, surveyed_leds

__all__ = ["AgentView", "agent_view", "nominal_intrinsics"]


@dataclass(frozen=True)
class AgentView:
    intrinsics: CameraIntrinsics
    led_map: LedMap
    mount: CameraMount


def nominal_intrinsics(world: World) -> CameraIntrinsics:
    """The world's camera as its calibration knows it, at output resolution."""
    cam = nominal_camera(world)
    cx, cy = cam.principal_point_px
    return CameraIntrinsics.from_sensor(
        sensor_width_px=cam.sensor_width_px,
        sensor_height_px=cam.sensor_height_px,
        output_width_px=cam.output_width_px,
        output_height_px=cam.output_height_px,
        focal_length_px=cam.focal_length_px,
        cx_sensor_px=cx,
        cy_sensor_px=cy,
        t_row_s=cam.t_row_s,
        exposure_s=cam.exposure_s,
        distortion=cam.distortion,
    )


def agent_view(world: World) -> AgentView:
    """The nominal camera, the surveyed LED map and the nominal mount."""
    leds = LedMap(tuple(MapLed.of(led) for led in surveyed_leds(world)))
    m = world.robot.camera_mount
    return AgentView(
        nominal_intrinsics(world), leds, CameraMount(m.x_m, m.y_m, m.z_m, m.yaw_rad, m.roll_rad, m.pitch_rad)
    )
