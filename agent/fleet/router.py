"""A Zenoh router in a Python process (``vlp-agent fleet router``): where a fleet's bridges meet when they
run in client mode (``[zenoh] mode = "client"``), instead of a peer mesh. ``eclipse-zenoh``'s session runs
the same router as ``zenohd`` (routing between its clients and peers, no storage, no admin REST plug-in);
it needs no other install. Scouting is off: the router is reached at its ``listen`` endpoints only, and
connects to other routers at its ``connect`` endpoints (tried again every ``retry_max_s`` when they go).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

from agent.fleet.bridge_config import ZenohConfig
from drivers.errors import DeviceNotFound

__all__ = ["open_router"]

log = logging.getLogger(__name__)


def open_router(listen: Sequence[str], connect: Sequence[str] = (), retry_max_s: float = 1.0) -> Any:
    """An open Zenoh session in router mode listening on ``listen``; :class:`DeviceNotFound` when an
    endpoint cannot be parsed or bound (another process on the port, say)."""
    import zenoh

    if not listen:
        raise ValueError("a router needs at least one listen endpoint")
    config = ZenohConfig("router", tuple(listen), tuple(connect), False, retry_max_s)
    try:
        session = zenoh.open(config.zenoh_config())
    except Exception as exc:  # zenoh's ZError
        raise DeviceNotFound(
            f"cannot open the Zenoh router (listen {list(listen)}, connect {list(connect)}): {exc}", "zenoh"
        ) from exc
    log.info("Zenoh router: listen %s, connect %s", list(listen), list(connect))
    return session
