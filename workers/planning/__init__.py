"""Zero-order trajectory optimisers of the CEM family (thesis chapter 3)."""

from workers.planning.config import CEM_BUDGETS, ICEM_BUDGETS, PRESETS, PlannerConfig
from workers.planning.icem import CEMPlanner, CostFunction, PlanResult
from workers.planning.noise import colored_noise, truncated_normal

__all__ = [
    "CEM_BUDGETS",
    "ICEM_BUDGETS",
    "PRESETS",
    "CEMPlanner",
    "CostFunction",
    "PlanResult",
    "PlannerConfig",
    "colored_noise",
    "truncated_normal",
]
