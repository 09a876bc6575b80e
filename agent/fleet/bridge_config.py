"""The bridge's config file (TOML, docs/fleet.md "Bridge config"): which robot, which agent socket, which
Zenoh endpoints. ``load_bridge_config(path)`` raises :class:`~drivers.errors.ConfigError` naming the key."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agent.fleet.local_protocol import valid_robot_name
from agent.fleet.ros2_out import Ros2Config, parse_ros2_table
from drivers.toml_table import TomlTable, read_toml, type_name

__all__ = ["BridgeConfig", "ZenohConfig", "load_bridge_config", "parse_bridge_config"]

_MODES = ("peer", "client")
_MAX_ENDPOINTS = 64
_RETRY_INIT_MS = 100


@dataclass(frozen=True)
class ZenohConfig:
    """``[zenoh]``: the session's mode (a bridge: peer or client; ``vlp-agent fleet router``: router), the
    endpoints it listens on and connects to (``tcp/HOST:PORT``, ...), whether it scouts for peers by
    multicast (off unless configured), and the longest wait between two tries to reach a ``connect``
    endpoint that went away (a router or peer restarting)."""

    mode: str = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    retry_max_s: float = 1.0

    def zenoh_config(self) -> Any:
        """A ``zenoh.Config`` (imports zenoh: only in the bridge and the fleet view)."""
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        # A lost connect endpoint is tried again after 0.1 s, then at doubling intervals up to retry_max_s
        # (Zenoh's own default: 1 s doubling to 4 s; a router back after a restart was then heard 2 s
        # after it listened again, here 0.5 s).
        retry = {
            "period_init_ms": min(_RETRY_INIT_MS, round(self.retry_max_s * 1000)),
            "period_max_ms": round(self.retry_max_s * 1000),
            "period_increase_factor": 2,
        }
        conf.insert_json5("connect/retry", json.dumps(retry))
        return conf


@dataclass(frozen=True)
class BridgeConfig:
    robot: str
    socket: Path
    zenoh: ZenohConfig
    key_prefix: str = "fleet"
    status_period_s: float = 1.0
    reconnect_s: float = 0.5
    file: str = "<bridge config>"
    ros2: Ros2Config = field(default_factory=Ros2Config)  # [ros2]: off unless enabled (ros2_out)


def load_bridge_config(path: str | os.PathLike[str]) -> BridgeConfig:
    file = os.fspath(path)
    return parse_bridge_config(read_toml(file, "the bridge config"), file)


def _string(t: TomlTable, name: str, default: str | None) -> str | None:
    if not t.has(name):
        return default
    value = t.take(name)
    if not isinstance(value, str):
        raise t.error(name, f"must be a string, not {type_name(value)}")
    return value


def _number(t: TomlTable, name: str, default: float, low: float, high: float) -> float:
    if not t.has(name):
        return default
    value = t.take(name)
    if type(value) not in (int, float) or not math.isfinite(value) or not low <= value <= high:
        raise t.error(name, f"must be a number {low:g}..{high:g}, not {value!r}")
    return float(value)


def _endpoints(t: TomlTable, name: str) -> tuple[str, ...]:
    if not t.has(name):
        return ()
    value = t.take(name)
    if not isinstance(value, list) or not all(isinstance(v, str) and "/" in v for v in value):
        raise t.error(name, f'must be an array of endpoints like "tcp/192.168.1.10:7447", not {value!r}')
    if len(value) > _MAX_ENDPOINTS:
        raise t.error(name, f"at most {_MAX_ENDPOINTS} endpoints")
    return tuple(value)


def parse_bridge_config(data: Mapping[str, Any], file: str = "<bridge config>") -> BridgeConfig:
    top = TomlTable(data, "", file)
    top.expect("bridge", "zenoh", "ros2")
    b = TomlTable(top.take("bridge") if top.has("bridge") else {}, "bridge", file)
    z = TomlTable(top.take("zenoh") if top.has("zenoh") else {}, "zenoh", file)
    robot = _string(b, "robot", None)
    if robot is None or not valid_robot_name(robot):
        raise b.error("robot", f"must be 1..32 letters, digits, '_' or '-', not {robot!r}")
    socket = _string(b, "socket", None)
    if not socket:
        raise b.error("socket", "the agent's [fleet] socket path is required")
    path = Path(os.path.expanduser(socket))
    if not path.is_absolute():
        path = (Path(file).resolve().parent if not file.startswith("<") else Path.cwd()) / path
    prefix = _string(b, "key_prefix", "fleet") or ""
    chunks = prefix.split("/")
    if not all(c and c not in ("*", "**") and not set(c) & set("?#$") for c in chunks):
        raise b.error("key_prefix", f"must be a key expression without wildcards, not {prefix!r}")
    mode = _string(z, "mode", "peer")
    if mode not in _MODES:
        raise z.error("mode", f"must be one of {list(_MODES)}, not {mode!r}")
    zenoh = ZenohConfig(
        mode=mode,
        listen=_endpoints(z, "listen"),
        connect=_endpoints(z, "connect"),
        multicast_scouting=z.boolean("multicast_scouting", False),
        retry_max_s=_number(z, "retry_max_s", 1.0, 0.1, 60.0),
    )
    if not zenoh.listen and not zenoh.connect and not zenoh.multicast_scouting:
        raise z.error("connect", "give listen or connect endpoints (or multicast_scouting = true)")
    config = BridgeConfig(
        robot=robot,
        socket=path,
        zenoh=zenoh,
        key_prefix=prefix,
        status_period_s=_number(b, "status_period_s", 1.0, 0.05, 60.0),
        reconnect_s=_number(b, "reconnect_s", 0.5, 0.05, 60.0),
        file=file,
        ros2=parse_ros2_table(top.take("ros2") if top.has("ros2") else {}, robot, file),
    )
    b.finish()
    z.finish()
    top.finish()
    return config
