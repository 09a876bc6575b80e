"""Navigation: costmap, global planner, local controller, collision monitor, recovery, and the navigator
that strings them together (``docs/navigation.md``). Pure algorithms: numpy in, numpy out, time passed in;
no threads, files or ports (like ``agent.slam``)."""

from agent.navigation.collision import CollisionMonitor, Verdict, Zone
from agent.navigation.config import NavConfig
from agent.navigation.controller import STOP, Command, PurePursuit
from agent.navigation.costmap import Costmap, GridSpec
from agent.navigation.navigator import Goal, Navigator, NavOutput, NavStatus
from agent.navigation.planner import GlobalPlanner, Plan, PlanStatus
from agent.navigation.recovery import Action, Recovery

__all__ = [
    "STOP",
    "Action",
    "CollisionMonitor",
    "Command",
    "Costmap",
    "GlobalPlanner",
    "Goal",
    "GridSpec",
    "NavConfig",
    "NavOutput",
    "NavStatus",
    "Navigator",
    "Plan",
    "PlanStatus",
    "PurePursuit",
    "Recovery",
    "Verdict",
    "Zone",
]
