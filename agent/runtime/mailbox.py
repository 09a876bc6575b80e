"""Hand-over between the runtime's threads: a one-slot "latest" mailbox and a small bounded queue.

Both drop instead of blocking the producer, and count what they drop. A camera frame goes through the
:class:`LatestMailbox`: a consumer that falls behind gets the newest frame and the older one is dropped,
so latency never grows. Scans and fixes go through a :class:`BoundedQueue`: a full queue drops its
*oldest* item (the consumer wants recent data), never silently.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Generic, TypeVar

__all__ = ["BoundedQueue", "LatestMailbox", "MailboxClosed"]

T = TypeVar("T")


class MailboxClosed(Exception):
    """The mailbox or queue was closed: the consumer should stop."""


class LatestMailbox(Generic[T]):
    """One slot. ``put`` replaces an unread item (counted in ``dropped``); ``take`` waits for one."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._item: T | None = None
        self._full = False
        self._closed = False
        self.put_count = 0
        self.taken = 0
        self.dropped = 0

    def put(self, item: T) -> bool:
        """Leave ``item`` for the consumer; True when it replaced one that was never taken."""
        with self._cond:
            if self._closed:
                raise MailboxClosed("mailbox is closed")
            replaced = self._full
            if replaced:
                self.dropped += 1
            self._item, self._full = item, True
            self.put_count += 1
            self._cond.notify()
            return replaced

    @property
    def pending(self) -> bool:
        """An item is waiting (read without the lock: a snapshot, for polling)."""
        return self._full

    def take(self, timeout_s: float) -> T | None:
        """The newest item, waiting up to ``timeout_s``; None on timeout. Raises MailboxClosed."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._full:
                if self._closed:
                    raise MailboxClosed("mailbox is closed")
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)
            item = self._item
            self._item, self._full = None, False
            self.taken += 1
            return item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._item, self._full = None, False
            self._cond.notify_all()


class BoundedQueue(Generic[T]):
    """FIFO of at most ``maxlen`` items; a put on a full queue drops the oldest (``dropped``)."""

    def __init__(self, maxlen: int) -> None:
        if maxlen < 1:
            raise ValueError(f"maxlen must be at least 1, got {maxlen}")
        self._items: collections.deque[T] = collections.deque()
        self.maxlen = maxlen
        self._cond = threading.Condition()
        self._closed = False
        self.put_count = 0
        self.dropped = 0

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

    def put(self, item: T) -> bool:
        """Queue ``item``; True when the oldest item had to be dropped for it."""
        with self._cond:
            if self._closed:
                raise MailboxClosed("queue is closed")
            dropped = len(self._items) >= self.maxlen
            if dropped:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self.put_count += 1
            self._cond.notify()
            return dropped

    def get(self, timeout_s: float) -> T | None:
        """The oldest item, waiting up to ``timeout_s``; None on timeout. Raises MailboxClosed."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._items:
                if self._closed:
                    raise MailboxClosed("queue is closed")
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return self._items.popleft()

    def drain(self) -> list[T]:
        """Everything queued now, without waiting."""
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
