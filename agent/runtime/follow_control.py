"""Following on command: the controller's follow frames (``FollowCommand``, ``docs/wire-format.md``) turn
the agent's follow loop on and off, and the loop's state goes back as goal statuses
(``docs/following.md``, "Following on command").

The command arbiter decides (``agent.runtime.arbiter``: a follow start is checked here, :meth:`check`, then
ranks with the controller's goal); this module only connects the arbiter to the follow loop:

* :meth:`FollowControl.check`: why a follow start cannot be taken, or None: FOLLOW_UNAVAILABLE when the
  agent has no follow loop (no laser, a forward camera without its lens...: the reason is logged),
  NO_TAG_READER when the command names a tag and the agent has no RFID layer to hear it with;
* :meth:`FollowControl.active` (the follow loop's ``active``): whether the arbiter has following in force;
  a new following (another follow id, another tag) restarts the loop and points the RFID layer at its tag
  (the command's, else ``[following] tag_id``);
* :meth:`FollowControl.on_step` (the loop's ``on_step``): each step's state as an ACTIVE status of the
  follow id, with a reason (:func:`wire_reason`) and the distance to the person as the remaining distance,
  when the reason changes (at most every ``min_gap_s``) and every ``period_s`` while it holds.

Thread-safe: :meth:`check` runs on the command loop's thread, the others on the follow loop's.
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable
from typing import Any

from agent.following.follower import FollowState
from agent.runtime.arbiter import STARTUP_FOLLOW_ID, CommandArbiter
from agent.runtime.follow_loop import NO_POSE, FollowLoop, FollowSnapshot
from firmware_protocol.command_frame import (
    NO_SEQUENCE,
    CommandType,
    FollowAction,
    FollowCommand,
    GoalReason,
    GoalStatus,
)

__all__ = ["FollowControl", "wire_reason"]

log = logging.getLogger(__name__)

SEARCHING_PREFIX = "searching"  # the follower's reason while it turns toward the RFID bearing


def wire_reason(snap: FollowSnapshot) -> GoalReason:
    """The follow loop's state as a status reason: FOLLOWING (followed, or waited for at the distance),
    SEARCHING (turning toward the RFID bearing), PERSON_LOST (no track or vanished: stopped), TAG_ABSENT,
    NO_CAMERA_FRAMES, NOT_LOCALIZED (no pose: stopped)."""
    state, why = snap.command.state, snap.command.reason
    if state in (FollowState.FOLLOWING, FollowState.WAITING):
        return GoalReason.FOLLOWING
    if state is FollowState.NO_TAG:
        return GoalReason.TAG_ABSENT
    if state is FollowState.NO_CAMERA:
        return GoalReason.NO_CAMERA_FRAMES
    if why == NO_POSE:
        return GoalReason.NOT_LOCALIZED
    if why.startswith(SEARCHING_PREFIX):
        return GoalReason.SEARCHING
    return GoalReason.PERSON_LOST


class FollowControl:
    """See the module's text. ``loop`` None: following is not set up (``unavailable`` says why); every
    follow start is then refused FOLLOW_UNAVAILABLE."""

    def __init__(
        self,
        arbiter: CommandArbiter,
        answer: Callable[[GoalStatus, CommandType | None], None],
        loop: FollowLoop | None,
        clock_s: Callable[[], float],
        *,
        coarse: Callable[[], Any] = lambda: None,
        configured_tag: str | None = None,
        unavailable: str = "",
        period_s: float = 1.0,
        min_gap_s: float = 0.25,
    ) -> None:
        self.arbiter = arbiter
        self.answer = answer
        self.loop = loop
        self.clock_s = clock_s
        self.coarse = coarse  # the agent's RFID layer (agent.runtime.rfid_loop.CoarseLayer) or None
        self.configured_tag = configured_tag
        self.unavailable = unavailable or "following is not set up"
        self.period_s = period_s
        self.min_gap_s = min_gap_s
        self.counts: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()
        self._current: FollowCommand | None = None  # the following the loop runs for
        self._sent: tuple[GoalReason, float] | None = None  # the last state reported, when
        self.last_reason: GoalReason | None = None
        self.last_why = ""
        arbiter.check_follow = self.check
        self._tag: str | None = configured_tag  # the tag followed now (None: none, acquisition ahead)
        if loop is not None:
            loop.active = self.active
            loop.on_step = self.on_step
            loop.coarse = self._loop_coarse

    # -- the command loop's side --------------------------------------------------------------------

    def check(self, command: FollowCommand) -> GoalReason | None:
        """Why the agent cannot start this following now, or None (called by the arbiter, under its lock)."""
        if self.loop is None:
            self.counts["refused_unavailable"] += 1
            log.warning("follow %d refused: %s", command.follow_id, self.unavailable)
            return GoalReason.FOLLOW_UNAVAILABLE
        if command.tag is not None and self.coarse() is None:
            self.counts["refused_no_tag_reader"] += 1
            log.warning(
                "follow %d refused: it names tag %s and the agent has no RFID reader ([rfid]) to hear it",
                command.follow_id,
                command.tag,
            )
            return GoalReason.NO_TAG_READER
        return None

    def start_now(self, tag: str | None = None) -> GoalStatus:
        """Start following as if commanded (``vlp-agent run --follow``: follow id ``STARTUP_FOLLOW_ID``);
        the answer (ACCEPTED, or REJECTED with why), also sent on the line."""
        statuses = self.arbiter.command(
            FollowCommand(NO_SEQUENCE, STARTUP_FOLLOW_ID, FollowAction.START, tag), self.clock_s()
        )
        for status in statuses:
            self.answer(status, CommandType.FOLLOW)
        return statuses[0]

    # -- the follow loop's side ---------------------------------------------------------------------

    def active(self) -> bool:
        """Whether to follow now; a new following restarts the loop on its tag."""
        follow = self.arbiter.following
        with self._lock:
            changed = follow is not self._current
            was = self._current
            self._current = follow
            if changed:
                self._sent = None
        if changed and follow is not None:
            self._retag(follow.tag)
            self.counts["followings"] += 1
            log.info(
                "following %d on: tag %s", follow.follow_id, follow.tag or self.configured_tag or "(none)"
            )
            if was is not None and self.loop is not None:
                self.loop.restart()  # another following while on: start afresh on it
        return follow is not None

    def _retag(self, tag: str | None) -> None:
        wanted = tag or self.configured_tag
        self._tag = wanted
        layer = self.coarse()
        if layer is not None and wanted is not None:
            layer.retag(wanted)

    def _loop_coarse(self) -> Any:
        """The RFID layer for the follow loop while a tag is followed; None without one (the loop then
        acquires ahead, as without a reader)."""
        return self.coarse() if self._tag is not None else None

    def on_step(self, snap: FollowSnapshot) -> None:
        """Report the step's state when it changed (after ``min_gap_s``) or every ``period_s``."""
        with self._lock:
            follow, sent = self._current, self._sent
        if follow is None:
            return
        reason = wire_reason(snap)
        self.last_reason, self.last_why = reason, snap.command.reason
        now = snap.t_s
        if sent is not None:
            last_reason, last_s = sent
            due = now - last_s >= (self.min_gap_s if reason is not last_reason else self.period_s)
            if not due:
                return
        distance = snap.command.distance_m if reason is GoalReason.FOLLOWING else None
        status = self.arbiter.follow_status(follow.follow_id, reason, distance)
        if status is None:  # ended meanwhile: its CANCELLED went out with the command that ended it
            return
        with self._lock:
            self._sent = (reason, now)
        self.counts[f"reported_{reason.name.lower()}"] += 1
        self.answer(status, CommandType.FOLLOW)

    def summary(self) -> dict[str, Any]:
        """For the final status: the following in force, the last state reported and why, the counts."""
        follow = self.arbiter.following
        return {
            "following": None if follow is None else follow.follow_id,
            "set_up": self.loop is not None,
            "unavailable": None if self.loop is not None else self.unavailable,
            "last_state": None if self.last_reason is None else self.last_reason.name,
            "last_why": self.last_why or None,
            "counts": dict(self.counts),
        }
