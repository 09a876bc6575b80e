"""The output loop: keeps the pose stream at ``output.rate_hz`` when nothing else writes (the camera
stalled, no fix); while the hot path writes poses it only sleeps."""

from __future__ import annotations

from collections.abc import Callable

from agent.runtime.health import Heartbeat
from agent.runtime.loop_state import LoopState
from agent.runtime.output import PoseOutput

__all__ = ["output_loop"]


def output_loop(
    state: LoopState,
    beat: Heartbeat,
    *,
    output: PoseOutput,
    publish: Callable[[int | None, int | None], None],
) -> None:
    """``publish(trigger_ns, arrival_ns)`` writes the fused pose."""
    period_ns = int(1e9 / state.config.output.rate_hz)
    while not state.stop.is_set():
        beat.beat()
        # Asleep until the floor rate calls for a pose (the camera's poses keep moving that time on):
        # a thread that wakes takes the interpreter lock, from the hot path if a frame is on it.
        due_ns = output.last_publish_ns + period_ns - state.clock_ns()
        state.stop.wait(min(max(due_ns, period_ns // 8), period_ns) * 1e-9)
        if state.stop.is_set():
            return
        if state.clock_ns() - output.last_publish_ns >= period_ns:
            publish(None, None)
