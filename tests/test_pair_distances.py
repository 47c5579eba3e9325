"""A collision distance per pair of agents (Collision.pair_distances; issue 29), against independent references:
- a 3-agent game of single integrators all pulled to the origin, so that at the end of the horizon every pair sits
  at its own distance: the triangle with sides 1, 2, 2 when pair (0, 1) (which starts 1.2 m apart) is relaxed to 1 m
  and the others keep 2 m (plane geometry); RD3G in both forms and both baselines, distances measured with numpy;
- the same as the scalar form when every pair is given the scalar value (same process: bit for bit);
- the best-response guess keeps each pair at its own distance plus the margin;
- a receding-horizon update that relaxes one pair solves as a fresh set-up does;
- validation in the Python API, in problem files (file and field named) and on the command line (exit code 2).
The constraint values and derivatives with distinct pair distances are checked against finite differences in
tests/test_derivatives.py, the second-order test in tests/test_second_order.py."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from app.cli import main
from bench.baselines import solve_algames, solve_ilqgames
from bench.merging import merging_problem
from bench.verify import stationarity_residual
from solver_cpp import (Agent, Collision, GameProblem, LinearModel, PairDistance, QuadraticCost, Solver, WarmStart,
                        solve)
from solver_cpp.best_response import best_response_guess
from solver_cpp.problem_file import ProblemFileError, problem_from_dict, problem_to_dict

NOMINAL_M = 2.0
RELAXED_M = 1.0


def _triangle(form: str = "distance", pairs=()) -> GameProblem:
    """Three single integrators p_{k+1} = p_k + u_k, each pulled to the origin; agents 0 and 1 start 1.2 m apart,
    closer than the nominal 2 m (as two cars after a contact), agent 2 4 m away."""
    cost = QuadraticCost(x_ref=(0.0, 0.0), Q_ref=(1.0, 1.0), R=(0.1, 0.1))
    agents = [Agent(LinearModel(np.eye(2), np.eye(2)), x0, cost) for x0 in [(-0.6, 0.0), (0.6, 0.0), (0.0, 4.0)]]
    return GameProblem(dt=1.0, horizon=4, agents=agents,
                       collision=Collision(NOMINAL_M, form=form, pair_distances=list(pairs)))


def _distances(x: np.ndarray) -> np.ndarray:
    """(N, N, T) distances between the agents' positions at k = 1..T."""
    p = x[:, 1:, :2]
    return np.linalg.norm(p[:, None] - p[None], axis=-1)


RELAX_01 = [PairDistance(agents=(1, 0), min_distance=RELAXED_M)]
# Own distance of each pair (0, 1), (0, 2), (1, 2) with pair (0, 1) relaxed; written out by hand.
OWN = {(0, 1): RELAXED_M, (0, 2): NOMINAL_M, (1, 2): NOMINAL_M}


@pytest.mark.parametrize("solver, form, tol_m", [
    ("rd3g", "distance", 1e-6), ("rd3g", "squared", 1e-6),
    # the baselines' penalty / augmented Lagrangian leave small violations
    ("ilqgames", "distance", 1e-4), ("algames", "distance", 1e-4)])
def test_each_pair_keeps_its_own_distance_and_the_relaxed_pair_comes_closer(solver, form, tol_m):
    run = {"rd3g": solve, "ilqgames": solve_ilqgames, "algames": solve_algames}[solver]
    result = run(_triangle(form, RELAX_01))
    assert result.status == "converged"
    d = _distances(result.x)
    for (i, j), own in OWN.items():
        assert d[i, j].min() >= own - tol_m, (i, j)
        # All three are pulled together, so at the end each pair sits at its own distance: sides 1, 2, 2.
        assert d[i, j, -1] == pytest.approx(own, abs=1e-3), (i, j)
    assert d[0, 1].min() < NOMINAL_M - 0.5  # the relaxed pair is allowed closer than the others
    if solver == "rd3g":
        # Independently of the solver: the KKT conditions of each player with its pairs' own distances.
        assert np.all(stationarity_residual(_triangle(form, RELAX_01), result.x, result.u, relative=True) <= 1e-6)
    # Without the relaxation every pair keeps the nominal distance (an equilateral triangle at the end).
    scalar = run(_triangle(form))
    assert _distances(scalar.x)[0, 1].min() >= NOMINAL_M - tol_m


@pytest.mark.parametrize("steps", [False, True])
def test_every_pair_at_the_scalar_value_is_the_scalar_form(steps):
    """Same process, same machine: the per-pair form with every pair at the scalar value (a number or per-step
    values, pairs in either order) gives the scalar form's result bit for bit, for RD3G and the baselines."""
    problem = merging_problem(3, 2)  # pair (0, 1) active at 2 m
    if steps:
        problem.collision.min_distance = np.linspace(1.8, 2.0, problem.horizon)
    d = problem.collision.min_distance
    per_pair = replace(problem, collision=replace(problem.collision, pair_distances=[
        PairDistance((0, 1), d), PairDistance((2, 0), d), PairDistance((1, 2), d)]))
    for run in (solve, solve_ilqgames, solve_algames):
        a, b = run(problem), run(per_pair)
        assert (a.status, a.iterations) == (b.status, b.iterations), run.__name__
        np.testing.assert_array_equal(a.x, b.x, err_msg=run.__name__)
        np.testing.assert_array_equal(a.u, b.u, err_msg=run.__name__)


def test_best_response_guess_keeps_each_pair_at_its_own_distance():
    """The guess's single-agent solves keep each other agent at its pair's distance times (1 + margin): 1.1 m for
    the relaxed pair, 2.2 m for the others, and all pulled to the origin they sit there."""
    margin = 0.1
    problem = _triangle("distance", RELAX_01)
    guess = best_response_guess(problem, rounds=2, best_response=dict(margin=margin))
    d = _distances(problem.rollout(guess.u))
    for (i, j), own in OWN.items():
        assert d[i, j].min() >= (1 + margin) * own - 1e-6, (i, j)
        assert d[i, j, -1] == pytest.approx((1 + margin) * own, abs=1e-3), (i, j)


def test_update_relaxes_one_pair_as_a_new_set_up_does():
    """A receding-horizon planner relaxes a pair through Solver.update (no new set-up); the result is the one of a
    solver set up with the relaxed problem, and an update back restores the nominal distance."""
    nominal, relaxed = _triangle(), _triangle(pairs=RELAX_01)
    solver = Solver(nominal)
    solver.solve()
    solver.update(relaxed)
    updated, fresh = solver.solve(), solve(relaxed)
    assert updated.setups == 0
    np.testing.assert_allclose(updated.x, fresh.x, atol=1e-9)
    solver.update(nominal)
    assert _distances(solver.solve(WarmStart(u=updated.u)).x)[0, 1].min() >= NOMINAL_M - 1e-6


# ------------------------------------------------------------------------------------------------------------
# Validation: each message names the field, the entry and the pair.
API_CASES = [
    ([PairDistance((0, 3), 1.0)], r"collision.pair_distances\[0\].agents must be two agent indices in \[0, 3\), got \[0, 3\]"),
    ([PairDistance((-1, 2), 1.0)], r"collision.pair_distances\[0\].agents must be two agent indices in \[0, 3\)"),
    ([PairDistance((1, 1), 1.0)], r"collision.pair_distances\[0\].agents must be two different agents, got \[1, 1\]"),
    ([PairDistance((0, 1), 1.0), PairDistance((1, 0), 1.2)],
     r"collision.pair_distances\[1\].agents: the pair \[1, 0\] already has a distance in collision.pair_distances\[0\]"),
    ([PairDistance((0, 2), -1.0)], r"collision.pair_distances\[0\].min_distance must be a positive finite number "
                                   r"\(m\), got -1 \(agents \[0, 2\]\)"),
    ([PairDistance((0, 2), float("nan"))], r"collision.pair_distances\[0\].min_distance must be a positive finite number "
                                           r"\(m\), got nan \(agents \[0, 2\]\)"),
    ([PairDistance((0, 2), float("inf"))], r"collision.pair_distances\[0\].min_distance must be a positive finite number "
                                           r"\(m\), got inf \(agents \[0, 2\]\)"),
    ([PairDistance((0, 2), [1.0] * 3)], r"collision.pair_distances\[0\].min_distance must be a positive number or 4 .*"
                                        r"got 3 \(agents \[0, 2\]\)"),
    ([PairDistance((2, 1), [1.0, 1.0, 0.0, 1.0])],
     r"collision.pair_distances\[0\].min_distance\[2\] \(step k = 3\) must be a positive finite number \(m\), got 0 "
     r"\(agents \[2, 1\]\)"),
    ([PairDistance((0,), 1.0)], r"collision.pair_distances\[0\].agents must be two agent indices, got \(0,\)"),
    ([PairDistance((0.5, 1), 1.0)], r"collision.pair_distances\[0\].agents\[0\] must be an integer"),
    ([(0, 1, 1.0)], r"collision.pair_distances\[0\] must be a PairDistance, got tuple"),
]


@pytest.mark.parametrize("pairs, message", API_CASES, ids=[str(i) for i in range(len(API_CASES))])
def test_api_validation_names_the_entry_and_the_pair(pairs, message):
    problem = _triangle(pairs=pairs)
    with pytest.raises(ValueError, match=message):
        problem.to_core()
    with pytest.raises(ValueError, match=message):  # and every solver that takes the problem
        solve_ilqgames(problem)
    with pytest.raises(ValueError, match=message):
        Solver(_triangle()).update(problem)


def _triangle_doc(pairs) -> dict:
    doc = problem_to_dict(_triangle())
    doc["collision"]["pair_distances"] = pairs
    return doc


def test_problem_file_round_trip_and_cli(tmp_path, capsys):
    problem = _triangle(pairs=[PairDistance((1, 0), RELAXED_M), PairDistance((1, 2), [2.0, 1.9, 1.8, 1.7])])
    doc = problem_to_dict(problem)
    assert doc["collision"]["pair_distances"] == [{"agents": [1, 0], "min_distance": 1.0},
                                                  {"agents": [1, 2], "min_distance": [2.0, 1.9, 1.8, 1.7]}]
    loaded, _, _ = problem_from_dict(json.loads(json.dumps(doc)))
    assert loaded.collision == problem.collision
    f, out = tmp_path / "p.json", tmp_path / "r.json"
    f.write_text(json.dumps(doc))
    assert main(["solve", str(f), "--out", str(out)]) == 0
    x = np.asarray(json.loads(out.read_text())["x"])
    d = _distances(x)
    assert d[0, 1].min() >= RELAXED_M - 1e-6 and d[0, 1].min() < NOMINAL_M - 0.5
    assert np.all(d[1, 2] >= np.array([2.0, 1.9, 1.8, 1.7]) - 1e-6) and d[0, 2].min() >= NOMINAL_M - 1e-6


FILE_CASES = [
    ([{"agents": [0, 5], "min_distance": 1.0}], "collision.pair_distances[0].agents must be two agent indices in [0, 3)"),
    ([{"agents": [0], "min_distance": 1.0}], "collision.pair_distances[0].agents: expected 2 values, got 1"),
    ([{"agents": [0, 1], "min_distance": -1.0}], "collision.pair_distances[0].min_distance: expected a finite number > 0"),
    ([{"agents": [0, 1]}], "collision.pair_distances[0].min_distance: missing"),
    ([{"agents": [0, 1], "distance": 1.0}], "collision.pair_distances[0].distance: unknown key 'distance'"),
    ([{"agents": [0, 1], "min_distance": 1.0}, {"agents": [1, 0], "min_distance": 1.5}],
     "collision.pair_distances[1].agents: the pair [1, 0] already has a distance in collision.pair_distances[0]"),
    ([{"agents": [2, 1], "min_distance": [1.0, 1.0]}],
     "collision.pair_distances[0].min_distance must be a positive number or 4 positive numbers"),
]


@pytest.mark.parametrize("pairs, message", FILE_CASES, ids=[str(i) for i in range(len(FILE_CASES))])
def test_problem_file_errors_name_file_and_field(tmp_path, capsys, pairs, message):
    f = tmp_path / "p.json"
    f.write_text(json.dumps(_triangle_doc(pairs)))
    with pytest.raises(ProblemFileError) as err:
        problem_from_dict(json.loads(f.read_text()), str(f))
    assert str(err.value).startswith(f"{f}: {message}"), str(err.value)
    assert main(["solve", str(f)]) == 2
    cli = capsys.readouterr().err.strip()
    assert cli.startswith(f"error: {f}: {message}") and "\n" not in cli, cli
