"""The agent process's runtime: device loops, the hot path, SLAM beside it, fusion, pose output, health.

:func:`create_agent` wires an :class:`~agent.runtime.agent.Agent` from a config: the devices by backend
name (on the simulated robot when the config has ``[sim]``), VLP and SLAM through their adapters when
their packages are usable (when not, the agent runs without them and says why), and the pose stream.

The names below are imported on first use (PEP 562): a child process that imports one module of this
package (``python -m agent.runtime.slam_worker``) does not load the whole agent with it (the recorder, the
device drivers, the pose output: memory the SLAM process has no use for).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from agent.runtime.agent import Agent, AgentStatus, DeviceState
    from agent.runtime.create import create_agent
    from agent.runtime.devices import Devices
    from agent.runtime.health import HealthMonitor
    from agent.runtime.localizer import FrameLocalizer
    from agent.runtime.mapper import ScanMapper
    from agent.runtime.output import PoseOutput, Written
    from agent.runtime.recorder import Recorder, replay

# name -> the module that defines it
_LAZY = {
    "Agent": "agent.runtime.agent",
    "AgentStatus": "agent.runtime.agent",
    "DeviceState": "agent.runtime.agent",
    "Devices": "agent.runtime.devices",
    "FrameLocalizer": "agent.runtime.localizer",
    "HealthMonitor": "agent.runtime.health",
    "PoseOutput": "agent.runtime.output",
    "Recorder": "agent.runtime.recorder",
    "ScanMapper": "agent.runtime.mapper",
    "Written": "agent.runtime.output",
    "create_agent": "agent.runtime.create",
    "replay": "agent.runtime.recorder",
}

__all__ = [
    "Agent",
    "AgentStatus",
    "DeviceState",
    "Devices",
    "FrameLocalizer",
    "HealthMonitor",
    "PoseOutput",
    "Recorder",
    "ScanMapper",
    "Written",
    "create_agent",
    "replay",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
