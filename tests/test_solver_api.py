"""Input validation of the solver API: bad input raises ValueError naming the field at fault, and no
input crashes the process (checked in child processes, so a segfault fails a test instead of the run)."""
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from bench.merging import merging_problem
from solver_cpp import (Collision, KinematicBicycle, KinematicBicycleFrenet, LinearModel, Obstacle, QuadraticCost,
                        Solver, WarmStart, solve)

REPO = Path(__file__).resolve().parents[1]


def _set(obj_path, value):
    """Mutation of a fresh 3-car merging problem: attribute path like 'agents.1.x0'."""
    def apply(problem):
        *parents, last = obj_path.split(".")
        obj = problem
        for name in parents:
            obj = obj[int(name)] if name.isdigit() else getattr(obj, name)
        setattr(obj, last, value)
    return apply


def _both(*mutations):
    def apply(problem):
        for m in mutations:
            m(problem)
    return apply


BAD_PROBLEMS = [
    ("x0 length", _set("agents.1.x0", [0.0, 0.0, 0.0]), "agents[1].x0"),
    ("x0 infinite", _set("agents.1.x0", [0.0, 0.0, np.inf, 0.0]), "agents[1].x0[2]"),
    ("x0 missing", _set("agents.2.x0", None), "agents[2].x0"),
    ("NaN in Q_ref", _set("agents.0.cost", QuadraticCost([0, 1, 2, 0], [0, np.nan, 0, 1], [1, 1])), "agents[0].cost.Q_ref[1]"),
    ("negative R", _set("agents.0.cost", QuadraticCost([0, 1, 2, 0], [0, 1, 0, 1], [-1, 1])), "agents[0].cost.R"),
    ("R length", _set("agents.2.cost", QuadraticCost([0, 1, 2, 0], [0, 1, 0, 1], [1, 1, 1])), "agents[2].cost.R"),
    ("dt zero", _set("dt", 0.0), "dt"),
    ("dt negative", _set("dt", -0.1), "dt"),
    ("dt NaN", _set("dt", float("nan")), "dt"),
    ("dt not a number", _set("dt", "fast"), "dt"),
    ("horizon zero", _set("horizon", 0), "horizon"),
    ("horizon fractional", _set("horizon", 2.5), "horizon"),
    ("horizon bool", _set("horizon", True), "horizon"),
    ("no agents", _set("agents", []), "agents"),
    ("mismatched model sizes", _set("agents.1.dynamics", LinearModel(np.eye(3), np.ones((3, 2)))), "agents[1].dynamics"),
    ("not a model", _set("agents.1.dynamics", "bicycle"), "agents[1].dynamics"),
    ("non-square A", _set("agents.0.dynamics", LinearModel(np.ones((4, 3)), np.ones((4, 2)))), "agents[0].dynamics.A"),
    ("zero lf", _set("agents.0.dynamics", KinematicBicycle(0.0, 1.0)), "agents[0].dynamics.lf"),
    ("NaN curvature", _set("agents.0.dynamics", KinematicBicycleFrenet(1, 1, [0, np.nan, 0], 1.0)), "agents[0].dynamics.kappa"),
    ("zero curvature spacing", _set("agents.0.dynamics", KinematicBicycleFrenet(1, 1, [0, 0.1, 0], 0.0)), "agents[0].dynamics.ds"),
    ("u_min >= u_max", _both(_set("agents.0.u_min", [-1, 0.5]), _set("agents.0.u_max", [1, 0.5])), "agents[0].u_min"),
    ("NaN u_min", _set("agents.0.u_min", [-1, np.nan]), "agents[0].u_min[1]"),
    ("x_min >= x_max", _both(_set("agents.2.x_min", [-np.inf, 2, 0, -np.inf]), _set("agents.2.x_max", [np.inf, 1, 5, np.inf])),
     "agents[2].x_min"),
    ("obstacle rows", _set("obstacles", [Obstacle(np.zeros((20, 2)), 1.0)]), "obstacles[0].positions"),
    ("obstacle columns", _set("obstacles", [Obstacle(np.zeros((21, 3)), 1.0)]), "obstacles[0].positions"),
    ("obstacle NaN", _set("obstacles", [Obstacle(np.full((21, 2), np.nan), 1.0)]), "obstacles[0].positions"),
    ("obstacle radius", _set("obstacles", [Obstacle(np.zeros((21, 2)), 0.0)]), "obstacles[0].min_distance"),
    ("collision form", _set("collision", Collision(2.0, form="manhattan")), "collision.form"),
    ("collision radius", _set("collision", Collision(-2.0)), "collision.min_distance"),
    ("collision position index", _set("collision", Collision(2.0, pos_y=7)), "collision.pos_y"),
    ("lead index", _set("agents.0.lead_index", 4), "agents[0].lead_index"),
    ("lead weight", _set("agents.0.lead_weight", np.inf), "agents[0].lead_weight"),
]


@pytest.mark.parametrize("mutate, field", [case[1:] for case in BAD_PROBLEMS], ids=[case[0] for case in BAD_PROBLEMS])
def test_bad_problem_is_rejected_naming_the_field(mutate, field):
    problem = merging_problem(3, 0)
    mutate(problem)
    with pytest.raises(ValueError) as err:
        solve(problem)
    assert field in str(err.value)


BAD_SETTINGS = [
    ({"foo": 1}, "solver.foo"),
    ({"linear": {"solver": "cholesky"}}, "solver.linear.solver"),
    ({"barrier": {"mode": "dual"}}, "solver.barrier.mode"),
    ({"max_iter": 2.5}, "solver.max_iter"),
    ({"tol": float("nan")}, "solver.tol"),
]


@pytest.mark.parametrize("settings, field", BAD_SETTINGS, ids=[s[1] for s in BAD_SETTINGS])
def test_bad_setting_is_rejected_naming_the_field(settings, field):
    with pytest.raises(ValueError) as err:
        solve(merging_problem(3, 0), **settings)
    assert field in str(err.value)


# Found while writing these tests; the C++ range check reports only "settings out of range".
SETTINGS_WITHOUT_FIELD_NAME = [
    ({"tol": -1.0}, "solver.tol"),
    ({"max_iter": -1}, "solver.max_iter"),
    ({"barrier": {"rho_kappa": 1.5}}, "solver.barrier.rho_kappa"),
    ({"line_search": {"beta": 2.0}}, "solver.line_search.beta"),
    ({"line_search": {"lm_tries": -1}}, "solver.line_search.lm_tries"),
    ({"tol": "abc"}, "solver.tol"),  # float('abc') error text, no field
    ({"linear": {"solver": 3}}, "solver.linear.solver"),  # pybind TypeError
    ({"restart": {"count": -1}}, "solver.restart.count"),  # accepted: no attempt runs, x returned as zeros (not x0)
    ({"violation_tol": -1.0}, "solver.violation_tol"),  # accepted: can never converge
    ({"time_limit": -1.0}, "solver.time_limit"),  # accepted as "no limit"
    ({"stall": {"polish_gap": -1.0}}, "solver.stall.polish_gap"),
    ({"stall": {"floor_window": -1}}, "solver.stall.floor_window"),
    ({"stall": {"crawl_window": -1}}, "solver.stall.crawl_window"),
    ({"stall": {"crawl_ratio": 0.0}}, "solver.stall.crawl_ratio"),
    ({"stall": {"crawl_ratio": 1.5}}, "solver.stall.crawl_ratio"),
    ({"line_search": {"violation_memory": 0}}, "solver.line_search.violation_memory"),
    ({"restart": {"violation_memory": 0}}, "solver.restart.violation_memory"),
    ({"restart": {"rho_progress": -1.0}}, "solver.restart.rho_progress"),
    ({"restart": {"deep_overlap": -0.5}}, "solver.restart.deep_overlap"),
    ({"second_order": {"escapes": -1}}, "solver.second_order.escapes"),
    ({"second_order": {"inertia": -1.0}}, "solver.second_order.inertia"),
    ({"best_response": {"rounds": -1}}, "solver.best_response.rounds"),
    ({"best_response": {"max_iter": 0}}, "solver.best_response.max_iter"),
    ({"best_response": {"margin": -0.1}}, "solver.best_response.margin"),
    ({"best_response": {"margin": float("inf")}}, "solver.best_response.margin"),
    ({"domain_fraction": 1.0}, "solver.domain_fraction"),
    ({"domain_fraction": -0.1}, "solver.domain_fraction"),
]


@pytest.mark.parametrize("settings, field", SETTINGS_WITHOUT_FIELD_NAME, ids=[str(s[0]) for s in SETTINGS_WITHOUT_FIELD_NAME])
def test_out_of_range_setting_is_rejected_naming_the_field(settings, field):
    with pytest.raises(ValueError) as err:
        solve(merging_problem(3, 0), **settings)
    assert field in str(err.value)


@pytest.mark.parametrize("warm, field", [
    (dict(u=np.zeros((3, 19, 2))), "warm_start.u"),
    (dict(u=np.full((3, 20, 2), np.nan)), "warm_start.u"),
    (dict(u=np.zeros((3, 20, 2)), lam=np.zeros((3, 20, 3))), "warm_start.lam"),
    (dict(u=np.zeros((3, 20, 2)), mu=np.zeros(5)), "warm_start.mu"),
], ids=["u shape", "u NaN", "lam shape", "mu shape"])
def test_bad_warm_start_is_rejected_naming_the_field(warm, field):
    solver = Solver(merging_problem(3, 0))
    with pytest.raises(ValueError) as err:
        solver.solve(WarmStart(**warm))
    assert field in str(err.value)
    assert solver.solve().status == "converged"  # the solver is still usable afterwards


def test_model_eval_rejects_wrong_sizes():
    f = KinematicBicycle(1.0, 1.0).build(0.1)
    with pytest.raises(ValueError):
        f.eval(np.zeros(3), np.zeros(2))
    with pytest.raises(ValueError):
        f.rollout(np.zeros(4), np.zeros((5, 3)))


def _run_child(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, capture_output=True, text=True,
                          timeout=120)


def test_bad_inputs_do_not_crash_the_process():
    """Every bad problem above plus malformed types, solved in a child process: each must raise an
    exception or return a result; the child must exit normally."""
    child = _run_child("""
        import numpy as np
        from tests.test_solver_api import BAD_PROBLEMS, SETTINGS_WITHOUT_FIELD_NAME
        from bench.merging import merging_problem
        from solver_cpp import Obstacle, solve
        cases = [(name, mutate, {}) for name, mutate, _ in BAD_PROBLEMS]
        cases += [(str(s), lambda p: None, s) for s, _ in SETTINGS_WITHOUT_FIELD_NAME]
        def set_(path, value):
            def apply(p):
                *parents, last = path.split(".")
                obj = p
                for n in parents:
                    obj = obj[int(n)] if n.isdigit() else getattr(obj, n)
                setattr(obj, last, value)
            return apply
        for path, value in [("agents.1.cost", None), ("agents", None), ("collision", "yes"), ("obstacles", None),
                            ("obstacles", [Obstacle(None, 1.0)]), ("horizon", 10**12), ("agents.0.lead_index", "s"),
                            ("agents.0.x0", [0.0, 1.1, 1e300, 0.0]), ("agents.0.x0", [1e308, 1e308, 1e308, 1e308])]:
            cases.append((path, set_(path, value), {}))
        for name, mutate, settings in cases:
            p = merging_problem(3, 0)
            try:
                mutate(p)
                solve(p, max_iter=3, **settings)
            except Exception:
                pass
        print("survived", len(cases))
    """)
    assert child.returncode == 0, child.stderr[-2000:]
    assert "survived" in child.stdout


@pytest.mark.parametrize("code", [
    """
    from solver_cpp import Agent, GameProblem, KinematicBicycleFrenet, QuadraticCost, solve
    cost = QuadraticCost([0, 0, 1, 0], [0, 1, 1, 1], [1, 1])
    solve(GameProblem(0.1, 5, [Agent(KinematicBicycleFrenet(1, 1, [1.0, 1.0], 1.0), [0, 1.0, 1, 0], cost)]))
    """,
    """
    import numpy as np
    from solver_cpp import KinematicBicycleFrenet
    f = KinematicBicycleFrenet(1, 1, [0.1, 0.2, 0.3], 1.0, closed=True).build(0.1)
    try:
        f.eval(np.array([np.nan, 0, 1, 0.0]), np.zeros(2))
    except ValueError:
        pass
    """,
], ids=["singular Frenet state in solve", "NaN arc length in eval"])
def test_frenet_singularity_does_not_crash(code):
    child = _run_child(code)
    assert child.returncode == 0, f"child exited with {child.returncode}: {child.stderr[-1000:]}"


@pytest.mark.parametrize("code", [
    """
    from bench.merging import merging_problem
    from solver_cpp import _core
    p = merging_problem(3, 0).to_core()
    p.dynamics = [None] + list(p.dynamics[1:])
    try:
        _core.Solver().setup(p, _core.Settings())
    except ValueError:
        pass
    """,
    """
    from bench.merging import merging_problem
    from solver_cpp import _core
    p = merging_problem(3, 0).to_core()
    p.lead = list(p.lead[:1])
    s = _core.Solver()
    try:
        s.setup(p, _core.Settings())
        assert False, "short lead list accepted"
    except ValueError:
        pass
    """,
    """
    import numpy as np
    from bench.merging import merging_problem
    from solver_cpp import Solver
    s = Solver(merging_problem(3, 0))
    try:
        s._solver.debug_residual([np.zeros((3, 4))], [np.zeros((2, 2))], [np.zeros((2, 4))], np.zeros(2), 0.1)
    except ValueError:
        pass
    """,
], ids=["missing first model", "short lead list", "debug_residual shapes"])
def test_core_rejects_malformed_problems(code):
    child = _run_child(code)
    assert child.returncode == 0, f"child exited with {child.returncode}: {child.stderr[-1000:]}"
