"""RD3G game solver: Python API over the C++ core (solver_cpp/src, bindings in solver_cpp/bindings)."""
from . import _core
from .models import KinematicBicycle, KinematicBicycleFrenet, LinearModel
from .problem import Agent, Collision, GameProblem, Obstacle, PairDistance, QuadraticCost
from .solve import GameResult, Solver, WarmStart, make_settings, merge_settings, settings_dict, solve

__all__ = [
    "_core", "KinematicBicycle", "KinematicBicycleFrenet", "LinearModel", "Agent", "Collision", "GameProblem",
    "Obstacle", "PairDistance", "QuadraticCost", "GameResult", "Solver", "WarmStart", "make_settings", "merge_settings",
    "settings_dict",
    "solve",
]
