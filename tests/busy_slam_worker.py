"""A SLAM process for the stop's tests (``python -m tests.busy_slam_worker FD``, set as
``ProcessMapper.worker_module``): the real one, except that once its map has had a filter update, the next
update never ends by itself. It goes on giving way (the filter's ``give_way``, where the stages of a real
update end) until the agent's stop makes that raise: a SLAM process busy in a long update, at any load.

``VLP_TEST_SLAM_BUSY``: a file it creates once it is in that update (the test's sign that it is busy).
``VLP_TEST_SLAM_STUCK=1``: it never gives way (a filter stuck in one long computation): only a kill ends it.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

from agent.config_slam import MountConfig, SlamConfig
from agent.runtime import slam_worker
from agent.runtime.mapper import MapperStep, Pose, RbpfMapper, ScanMapper
from drivers.samples import Scan


class BusyMapper(RbpfMapper):
    def update(self, scan: Scan, odom_pose: Pose) -> MapperStep:
        if self.counters().get("filter_updates", 0) >= 1:
            busy = os.environ.get("VLP_TEST_SLAM_BUSY")
            if busy:
                Path(busy).touch()
            stuck = os.environ.get("VLP_TEST_SLAM_STUCK") == "1"
            while True:
                if not stuck:
                    self.give_way()
                time.sleep(0.02)
        return super().update(scan, odom_pose)


def busy_mapper(
    config: SlamConfig, mount: MountConfig, start_pose: Callable[[int], Pose | None]
) -> tuple[ScanMapper | None, str]:
    """``make_local_mapper`` for a mapping config, with the busy filter."""
    return BusyMapper(config, mount, start_pose), ""


if __name__ == "__main__":
    slam_worker.make_local_mapper = busy_mapper
    sys.exit(slam_worker.main())
