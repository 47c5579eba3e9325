"""Every index a problem carries is checked against the size it refers to, whatever blocks are present
(issue 17: a one-state linear agent with an obstacle and no collision block corrupted the heap, because
the obstacle's position indices were only checked with a collision block). Each case runs in a child
process, so a native abort fails the test instead of killing pytest."""
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

ONE_STATE_WITH_OBSTACLE = {
    "dt": 0.1, "horizon": 3,
    "agents": [{"dynamics": {"type": "linear", "A": [[1.0]], "B": [[0.1]]}, "x0": [0.0],
                "cost": {"x_ref": [1.0], "Q_ref": [1.0], "R": [0.1]}}],
    "obstacles": [{"positions": [[0.0, 0.0]] * 4, "min_distance": 0.5}],
}


def _child(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, capture_output=True, text=True,
                          timeout=120)


def test_cli_solve_of_the_one_state_obstacle_problem_exits_2_naming_the_field(tmp_path):
    path = tmp_path / "problem.json"
    path.write_text(json.dumps(ONE_STATE_WITH_OBSTACLE))
    run = subprocess.run([sys.executable, "-m", "app", "solve", str(path)], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 2, (run.returncode, run.stderr[-1000:])
    assert "collision.pos_y" in run.stderr and "[0, 1)" in run.stderr


CASES = {
    # The same problem through the Python API, RD3G and both baselines.
    "python api": """
        from solver_cpp import Agent, GameProblem, LinearModel, Obstacle, QuadraticCost, solve
        p = GameProblem(0.1, 3, [Agent(LinearModel([[1.0]], [[0.1]]), [0.0], QuadraticCost([1.0], [1.0], [0.1]))],
                        obstacles=[Obstacle([[0.0, 0.0]] * 4, 0.5)])
        check(lambda: solve(p), "collision.pos_y")
    """,
    "baselines": """
        from solver_cpp import Agent, GameProblem, LinearModel, Obstacle, QuadraticCost, _core
        p = GameProblem(0.1, 3, [Agent(LinearModel([[1.0]], [[0.1]]), [0.0], QuadraticCost([1.0], [1.0], [0.1]))],
                        obstacles=[Obstacle([[0.0, 0.0]] * 4, 0.5)]).to_core(validate=False)
        check(lambda: _core.ILQGamesSolver().setup(p, _core.ILQGamesSettings()), "collision.pos_y")
        check(lambda: _core.ALGamesSolver().setup(p, _core.ALGamesSettings()), "collision.pos_y")
    """,
    # Indices and sizes set directly on the C++ structs, past the Python conversion.
    "core indices": """
        import numpy as np
        from bench.merging import merging_problem
        from solver_cpp import _core
        def core(mutate):
            p = merging_problem(2, 0).to_core(validate=False)
            mutate(p)
            return lambda: _core.Solver().setup(p, _core.Settings())
        def lead(p):
            l = _core.LeadCost(); l.weight = 1.0; l.index = 9
            p.lead = [l, l]
        check(core(lead), "agents[0].lead_index")
        def pos(p):
            c = p.collision; c.pos_y = -1; p.collision = c
        check(core(pos), "collision.pos_y")
        def obstacle(p):
            o = _core.Obstacle(); o.positions = np.zeros((5, 2)); o.min_distance = 1.0
            p.obstacles = [o]
        check(core(obstacle), "obstacles[0].positions")
        def steps(p):
            c = p.collision; c.min_distance_steps = np.ones(3); p.collision = c
        check(core(steps), "collision.min_distance")
        def bounds(p):
            p.x_max = [np.ones(4), np.ones(2)]
        check(core(bounds), "agents[1].x_max")
        def x0(p):
            p.x0 = [np.zeros(4)]
        check(core(x0), "x0 must have one entry per agent")
    """,
}


@pytest.mark.parametrize("code", CASES.values(), ids=CASES.keys())
def test_bad_indices_raise_value_error_naming_the_field(code):
    prelude = """
        def check(call, field):
            try:
                call()
            except ValueError as exc:
                assert field in str(exc), (field, str(exc))
            else:
                raise AssertionError(f"accepted: {field}")
    """
    child = _child(textwrap.dedent(prelude) + textwrap.dedent(code))
    assert child.returncode == 0, f"child exited with {child.returncode}: {child.stderr[-1500:]}"
