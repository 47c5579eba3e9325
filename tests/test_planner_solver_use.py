"""How the racing planners use the solver: settings pass through under the solver's own names (defaults
only in solver_cpp/include/rd3g/problem.hpp), and each planner sets its solver up once and updates it at
every later plan."""
import numpy as np
import pytest

from planning import CommandMapper, FrenetTrackModel, MPCOpponent, PlannerConfig, RacingPlanner
from planning.config import PlannerConfigError, solver_settings
from solver_cpp import _core

PERIOD = 1.0 / 30.0


def test_solver_settings_are_the_solvers_own_names():
    with pytest.raises(PlannerConfigError, match=r"planner.solver: solver.max_iterations"):
        PlannerConfig(solver={"max_iterations": 15})
    with pytest.raises(PlannerConfigError, match=r"planner.cold_start_solver: solver.tol"):
        PlannerConfig(cold_start_solver={"tol": -1.0})
    cfg = PlannerConfig()
    defaults = _core.Settings()  # the C++ defaults, read from the struct itself
    warm = solver_settings(cfg.solver)
    cold = solver_settings(cfg.solver, cfg.cold_start_solver)
    assert (warm.max_iter, warm.restart.count, warm.line_search.lm_tries, warm.barrier.rho_init) == (15, 0, 0, 1e-3)
    # None = the solver's default: the cold start gets the solver's Levenberg-Marquardt and line-search steps; its
    # barrier weight is the warm plans'.
    assert (cold.line_search.lm_tries, cold.line_search.max_steps) == \
        (defaults.line_search.lm_tries, defaults.line_search.max_steps)
    assert cold.barrier.rho_init == warm.barrier.rho_init
    assert (cold.max_iter, cold.restart.count, cold.barrier.rho_progress) == (200, 3, warm.barrier.rho_progress)
    assert warm.tol == cold.tol == defaults.tol


@pytest.mark.parametrize("cls, kw", [(RacingPlanner, {"opponent_top_speed_mps": 1.8}), (MPCOpponent, {})],
                         ids=["rd3g", "mpc"])
def test_planner_sets_the_solver_up_once_and_updates_it(track, car, cls, kw):
    cfg = PlannerConfig()
    planner = cls(FrenetTrackModel(track, car, cfg), CommandMapper(car, PERIOD), cfg, PERIOD, **kw)
    x_self, x_other = np.array([0.8, 0.1, 1.5, 0.0]), np.array([1.3, -0.05, 1.4, 0.0])
    planner.plan(x_self, x_other)
    solver = planner._solver
    for step in range(4):
        x_self = x_self + np.array([0.05, 0.0, 0.0, 0.0])
        x_other = x_other + np.array([0.05, 0.0, 0.0, 0.0])
        planner.plan(x_self, x_other)
        assert planner._solver is solver
        result = planner._prev
        assert result.setups == 0 and result.update_time_s > 0  # updated, not set up again
        np.testing.assert_allclose(result.x[0, 0], x_self)
        assert solver.settings.max_iter == cfg.solver["max_iter"]
