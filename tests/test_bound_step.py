"""Steps stop before the bounds (Settings::line_search.to_crossing, docs/solver.md "Backtracking to just before a
crossing"): state and control bounds are linear in the variables, so the game's line search starts at 0.99 of the
step to the first bound it would cross instead of trying the full step and halving.

The merging car of a merge-long game, alone, with its steering bounded at 0.6 rad: with the rule off (the paper's
line search) full Newton steps cross the bound and are rejected by the violation test; with it on no trial is. Both
reach the same optimum, which SLSQP over the car's controls (bench.verify.best_response_gap, an independent
optimiser) cannot improve."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench import verify
from bench.families import family_problem
from solver_cpp import GameProblem

ROOT = Path(__file__).resolve().parents[1]
BOUND = 0.6

# Each solve in its own process: the solver's verbose trace is C stdio, flushed when the process ends.
_SOLVE = """
import json, sys
from bench.families import family_problem
from solver_cpp import GameProblem, solve
p = family_problem("merge-long", 2, 0)
alone = GameProblem(dt=p.dt, horizon=p.horizon, agents=[p.agents[1]], collision=p.collision)
r = solve(alone, line_search=dict(to_crossing=sys.argv[1] == "on"), verbose=True)
sys.stdout.flush()
print("RESULT " + json.dumps({"status": r.status, "u": r.u.tolist(), "x": r.x.tolist()}))
"""


def _solve(rule: str) -> tuple[dict, int]:
    out = subprocess.run([sys.executable, "-c", _SOLVE, rule], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout
    result = json.loads(next(line[len("RESULT "):] for line in out.splitlines() if line.startswith("RESULT ")))
    return result, sum("rejected: violation" in line for line in out.splitlines())


@pytest.fixture(scope="module")
def merging_car():
    p = family_problem("merge-long", 2, 0)
    assert p.agents[1].u_min[1] == -BOUND and p.agents[1].u_max[1] == BOUND and np.isinf(p.agents[1].u_max[0])
    return GameProblem(dt=p.dt, horizon=p.horizon, agents=[p.agents[1]], collision=p.collision)


def test_no_trial_crosses_a_bound(merging_car):
    off, rejected_off = _solve("off")
    on, rejected_on = _solve("on")
    assert rejected_off > 0  # the situation the rule is for: full steps across the steering bound
    assert rejected_on == 0
    assert off["status"] == on["status"] == "converged"
    u_on = np.asarray(on["u"])
    assert np.abs(u_on[0, :, 1]).max() <= BOUND  # (acceleration, steering)
    np.testing.assert_allclose(u_on, np.asarray(off["u"]), atol=1e-5, rtol=0)
    gap = verify.best_response_gap(merging_car, np.asarray(on["x"]), u_on, 0, starts=2, seed=0)
    assert gap <= 1e-4  # the barrier at its floor leaves an O(rho) perturbation
