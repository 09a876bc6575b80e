"""Sending a goal to one robot of the fleet and hearing its statuses (``vlp-agent fleet goal``).

The goal goes out on ``<prefix>/<robot>/goal`` (JSON, ``agent.fleet.payloads``) once the robot's bridge is
known to subscribe there (Zenoh's matching status: a put before that would go nowhere); its statuses come
back on ``<prefix>/<robot>/goal_state`` with the goal's id. Only the robot's bridge acts on it: it accepts
goals under its own name only, and its agent drives them under the local command precedence
(``agent.runtime.arbiter``). Statuses of other goal ids and malformed ones are ignored (counted).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

from agent.fleet import payloads
from agent.fleet.bridge_config import ZenohConfig
from agent.fleet.local_protocol import GoalMessage, GoalStateMessage
from firmware_protocol.command_frame import GoalState
from firmware_protocol.errors import ProtocolError

__all__ = ["ENDED", "GoalSender", "GoalTrace"]

ENDED = frozenset({GoalState.REJECTED, GoalState.REACHED, GoalState.FAILED, GoalState.CANCELLED})


@dataclass
class GoalTrace:
    """What became of one goal: whether it went out (a bridge subscribed), the statuses heard, in order."""

    sent: bool = False
    states: list[GoalStateMessage] = field(default_factory=list)
    ignored: int = 0

    @property
    def last(self) -> GoalStateMessage | None:
        return self.states[-1] if self.states else None

    @property
    def ended(self) -> bool:
        return self.last is not None and self.last.state in ENDED


class GoalSender:
    def __init__(self, zenoh: ZenohConfig, key_prefix: str = "fleet") -> None:
        self.zenoh = zenoh
        self.key_prefix = key_prefix

    def send(self, robot: str, goal: GoalMessage, *, wait_end: bool, timeout_s: float) -> GoalTrace:
        """Publish ``goal`` for ``robot`` and listen for its statuses until the first (``wait_end``
        False) or until it ended (REACHED, FAILED, REJECTED, CANCELLED), at most ``timeout_s``."""
        import zenoh

        trace = GoalTrace()
        heard = threading.Condition()

        def on_state(sample: Any) -> None:
            try:
                state = payloads.decode_goal_state(bytes(sample.payload.to_bytes()), robot)
            except ProtocolError:
                state = None
            with heard:
                if state is None or state.goal_id != goal.goal_id:
                    trace.ignored += 1
                    return
                trace.states.append(state)
                heard.notify_all()

        deadline = time.monotonic() + timeout_s
        session: Any = zenoh.open(self.zenoh.zenoh_config())
        try:
            sub = session.declare_subscriber(payloads.key(self.key_prefix, robot, "goal_state"), on_state)
            publisher = session.declare_publisher(payloads.key(self.key_prefix, robot, "goal"))
            while not publisher.matching_status.matching:
                if time.monotonic() >= deadline:
                    return trace  # no bridge of that robot subscribes: not sent
                time.sleep(0.05)
            # Our subscription was declared first on the same links, so the bridge knows it by now.
            publisher.put(payloads.encode_goal(robot, goal))
            trace.sent = True
            with heard:
                while not (trace.ended if wait_end else trace.states):
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        break
                    heard.wait(min(remaining, 0.5))
            publisher.undeclare()
            sub.undeclare()
        finally:
            session.close()
        return trace
