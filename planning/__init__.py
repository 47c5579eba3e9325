"""Racing planners on the track (docs/racing.md).

* :class:`RacingPlanner` -- RD3G: a 2-car dynamic game in Frenet coordinates solved by the project's
  C++ solver, receding horizon, warm-started from the previous plan.
* :class:`MPCOpponent` -- single-car optimal control with the same cost that predicts the other car
  at constant speed along the track and avoids that prediction (it ignores the interaction).
* :class:`PurePursuitController` -- a geometric path follower at a target speed (opponent, sysid excitation).
* :class:`CommandMapper` -- planned [a, delta] to the car's [throttle, steering] (inverse
  longitudinal model, [corrections] of the car file, delay compensation).
"""
from .commands import CommandMapper
from .config import PlannerConfig
from .frenet import FrenetTrackModel, ProgressUnwrapper, frenet_state
from .pursuit import PurePursuitController
from .racing import MPCOpponent, Plan, RacingPlanner

__all__ = ["CommandMapper", "FrenetTrackModel", "MPCOpponent", "Plan", "PlannerConfig", "ProgressUnwrapper",
           "PurePursuitController", "RacingPlanner", "frenet_state"]
