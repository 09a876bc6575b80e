"""Which laser localizer the agent runs: in this process, or in a child process (``slam.process``).

Apart from :mod:`agent.runtime.mapper` (the filters and their types) and :mod:`agent.runtime.slam_worker`
(the child process, which builds its filter with ``make_local_mapper``) so that neither imports the other.
"""

from __future__ import annotations

from collections.abc import Callable

from agent.config import MountConfig, SlamConfig
from agent.runtime.mapper import Pose, ScanMapper, make_local_mapper

__all__ = ["make_mapper"]


def make_mapper(
    config: SlamConfig, mount: MountConfig, start_pose: Callable[[int], Pose | None]
) -> tuple[ScanMapper | None, str]:
    """The laser localizer for this config (mapping or localization on a map), or None and the reason it is
    not available; with ``config.process``, run in a child process (``agent.runtime.slam_worker``)."""
    if not config.enabled:
        return None, "disabled in the config"
    if not config.process:
        return make_local_mapper(config, mount, start_pose)
    from agent.runtime.slam_worker import ProcessMapper

    try:
        return ProcessMapper(config, mount, start_pose), ""
    except ImportError as exc:
        return None, f"the SLAM package is not usable: {exc}"
    except ValueError as exc:
        return None, str(exc)
