"""The garbage collector run between frames: off elsewhere, CPython's thresholds, back on at stop."""

from __future__ import annotations

import gc
import weakref

from agent.runtime.collector import IdleCollector


class _Node:
    def __init__(self) -> None:
        self.me = self  # a reference cycle: only the cyclic collector frees it


def test_collects_only_when_asked_and_hands_back() -> None:
    was_enabled = gc.isenabled()
    collector = IdleCollector(full_interval_s=1e9)
    assert collector.collect_if_due() is None  # not started: nothing to do
    collector.start()
    try:
        assert not gc.isenabled()
        node = _Node()
        ref = weakref.ref(node)
        del node
        # More new objects than the youngest generation's threshold: CPython would have collected by now.
        keep = [[] for _ in range(2 * gc.get_threshold()[0])]
        assert ref() is not None
        generation = collector.collect_if_due()
        assert generation in (0, 1)
        assert ref() is None
        assert sum(collector.collections) == 1
        # Nothing new since: not due.
        assert collector.collect_if_due() is None
        del keep
    finally:
        collector.stop()
    assert gc.isenabled() == was_enabled
    collector.stop()  # twice is fine
    assert gc.isenabled() == was_enabled


def test_generations_follow_the_thresholds_and_full_passes_are_paced() -> None:
    now = [0.0]
    collector = IdleCollector(full_interval_s=60.0, clock=lambda: now[0])
    collector.start()
    try:
        t0, t1, t2 = gc.get_threshold()
        seen: list[int] = []
        keep = []
        for _ in range(t1 * t2 + 5):
            keep.append([[] for _ in range(t0 + 1)])
            g = collector.collect_if_due()
            assert g is not None
            seen.append(g)
        # A middle collection every t1-th time, no full one within the interval.
        assert seen.count(1) >= t2 - 1 and 2 not in seen
        now[0] = 61.0
        while True:
            keep.append([[] for _ in range(t0 + 1)])
            g = collector.collect_if_due()
            if g != 0:
                break
        assert g == 2
    finally:
        collector.stop()


def test_an_absent_hot_path_hands_collection_back() -> None:
    was_enabled = gc.isenabled()
    now = [0.0]
    collector = IdleCollector(max_absence_s=2.0, clock=lambda: now[0])
    collector.start()
    try:
        now[0] = 1.5
        assert not collector.check() and collector.active
        collector.collect_if_due()  # the hot path came by at 1.5 s
        now[0] = 3.0
        assert not collector.check()
        now[0] = 3.6  # 2.1 s since: its loop died or hangs
        assert collector.check()
        assert not collector.active and gc.isenabled() == was_enabled
        assert collector.collect_if_due() is None
    finally:
        collector.stop()
