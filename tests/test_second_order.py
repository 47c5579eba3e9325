"""The solver's second-order test (Info::second_order, status 'saddle') against independent references:
- a game of two single integrators, each with a disc in its way, whose first-order point in front of the disc
  has the analytic reduced-Hessian eigenvalue 6R - 4F (a saddle for F > 1.5 R, a strict minimum below);
- unconstrained LQ games, where each player's reduced Hessian is the batch Hessian 2 blkdiag(R) + S'QS of its
  cost in its controls, built here from A, B and the weights;
- merging games with active collision constraints (one with its own distance per pair) and control bounds, against
  a finite-difference Hessian of
  each player's shooting Lagrangian U -> J(x(U), U) + sum_c mu_c h_c(x(U), U) projected on the null space of
  its active constraints (scipy), computed from the trajectories and multipliers the solver returns;
- the extreme eigenvalues of the tridiagonal form (Sturm bisection) against LAPACK's (numpy.linalg.eigvalsh);
- the lscg case in tests/test_merging_equilibria.py (a first-order point that unilateral deviations improve) is
  tested there."""
import numpy as np
import pytest
from scipy.linalg import null_space

from bench.merging import merging_problem
from bench.verify import BEST_RESPONSE_TOL, best_response_gap, player_cost, stationarity_residual
from solver_cpp import Agent, Collision, GameProblem, LinearModel, Obstacle, PairDistance, QuadraticCost, _core, solve
from solver_cpp.problem_file import result_to_dict


def _disc_game(R: float, F: float) -> GameProblem:
    """Two single integrators p_1 = p_0 + u (one step) from (-3, 0) and (-3, 100) to (2, 0) and (2, 100), each with
    a disc of radius 1 (squared form) in its way at (0, 0) and (0, 100); the players are 100 m apart, so their own
    pair constraint is slack. The first-order point in front of the disc, p = (-1, 0) (resp. (-1, 100)), has
    multiplier mu = 3F - 2R (> 0 for F > 2R/3), and on the active constraint's null space (u_y) the curvature
    2R + 2F - 2 mu = 6R - 4F: a saddle of each player's problem for F > 1.5 R, a strict minimum below."""
    def agent(y):
        return Agent(LinearModel(np.eye(2), np.eye(2)), (-3.0, y), QuadraticCost(x_ref=(2.0, y), Q_ref=(F, F), R=(R, R)))
    discs = [Obstacle(np.array([[0.0, y], [0.0, y]]), min_distance=1.0) for y in (0.0, 100.0)]
    return GameProblem(dt=1.0, horizon=1, agents=[agent(0.0), agent(100.0)], collision=Collision(1.0, form="squared"),
                       obstacles=discs)


@pytest.mark.parametrize("R, F", [(1.0, 2.0), (1.0, 3.0), (1.0, 1.0), (1.0, 1.2)])
def test_disc_game_analytic_eigenvalue(R, F):
    problem = _disc_game(R, F)
    result = solve(problem, tol=1e-9)
    np.testing.assert_allclose(result.x[:, 1], [[-1.0, 0.0], [-1.0, 100.0]], atol=1e-6)
    np.testing.assert_allclose(result.second_order, [6 * R - 4 * F] * 2, rtol=1e-5)
    assert result.status == ("saddle" if 6 * R < 4 * F else "converged")
    assert result_to_dict(result)["second_order"] == pytest.approx([6 * R - 4 * F] * 2, rel=1e-5)


def test_disc_game_saddle_is_not_an_equilibrium():
    """Independently of any Hessian: at the saddle player 0 lowers its cost by sliding round its disc."""
    problem = _disc_game(1.0, 2.0)
    result = solve(problem, tol=1e-9)
    x, u = result.x.copy(), result.u.copy()
    J0 = player_cost(problem, x, u, 0)
    angle = 0.3
    x[0, 1] = np.array([-np.cos(angle), np.sin(angle)])
    u[0, 0] = x[0, 1] - x[0, 0]
    assert player_cost(problem, x, u, 0) < J0 - 1e-2


def _batch_hessian(A, B, R, Qs, Qf, T):
    """Hessian of sum_k u_k'R u_k + sum_{k=1}^{T-1} x_k'Q x_k + x_T'Qf x_T in U = (u_0..u_{T-1}), x_0 fixed."""
    nx, nu = B.shape
    H = np.kron(np.eye(T), 2 * np.diag(R))
    S = np.zeros((nx, T * nu))
    for k in range(T):
        S = A @ S
        S[:, k * nu:(k + 1) * nu] += B
        W = np.diag(Qf if k == T - 1 else Qs)
        H += 2 * S.T @ W @ S
    return H


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lq_game_eigenvalue_is_the_batch_hessian(seed):
    rng = np.random.default_rng(seed)
    T, nx, nu = 6, 3, 2
    agents, expected = [], []
    for _ in range(2):
        A = rng.normal(size=(nx, nx))
        B = rng.normal(size=(nx, nu))
        R, Q_ref, Q, F = rng.uniform(0.1, 1, nu), rng.uniform(0, 1, nx), rng.uniform(0, 0.5, nx), rng.uniform(0, 2, nx)
        agents.append(Agent(LinearModel(A, B), rng.normal(size=nx),
                            QuadraticCost(x_ref=rng.normal(size=nx), Q_ref=Q_ref, Q=Q, R=R, Qf_ref=F, Qf=0 * F)))
        expected.append(np.linalg.eigvalsh(_batch_hessian(A, B, R, Q_ref + Q, F, T))[0])
    result = solve(GameProblem(dt=0.1, horizon=T, agents=agents), tol=1e-9)
    assert result.status == "converged"
    np.testing.assert_allclose(result.second_order, expected, rtol=1e-8)


# ------------------------------------------------------------------------------------------------------------
def _fd_reduced_min_eigenvalue(problem, result, a, gap=1e-2, step=1e-4):
    """Smallest eigenvalue of the finite-difference Hessian of player a's shooting Lagrangian on the null space of
    its active constraints (h >= -gap, multiplier > 0). Pair constraints in the squared form and control bounds
    (the kinds the cases use), written from their definitions."""
    T, nu = result.u.shape[1], result.u.shape[2]
    f = problem.agents[a].dynamics.build(problem.dt)
    agent = problem.agents[a]
    pairs = [(ci, c.k, c.j if c.i == a else c.i) for ci, c in enumerate(result.constraints)
             if c.kind.name == "pair" and a in (c.i, c.j)]
    bounds = [(ci, c.k, c.idx, 1.0 if c.kind.name == "control_max" else -1.0) for ci, c in enumerate(result.constraints)
              if c.kind.name in ("control_max", "control_min") and c.i == a]
    assert len(pairs) + len(bounds) == sum(a in (c.i, c.j) for c in result.constraints)
    pk = np.array([k for _, k, _ in pairs], dtype=int)
    pj = np.array([j for _, _, j in pairs], dtype=int)
    others = result.x[pj, pk, :2]
    d = problem.collision.pair_min_distances(problem.num_agents, T)[a, pj, pk - 1]  # each pair's own d_min
    mu = result.mu[[ci for ci, _, _ in pairs] + [ci for ci, _, _, _ in bounds]]

    def constraint_values(U):
        u = U.reshape(T, nu)
        xa = f.rollout(result.x[a, 0], u)
        h_pair = d * d - np.sum((xa[pk, :2] - others) ** 2, axis=1)
        h_bound = [s * u[k, q] - (agent.u_max[q] if s > 0 else -agent.u_min[q]) for _, k, q, s in bounds]
        return xa, np.concatenate([h_pair, h_bound])

    def lagrangian(U):
        xa, h = constraint_values(U)
        x, u = result.x.copy(), result.u.copy()
        x[a], u[a] = xa, U.reshape(T, nu)
        return player_cost(problem, x, u, a) + mu @ h

    U0 = result.u[a].ravel()
    m = U0.size
    E = np.eye(m) * step
    H = np.zeros((m, m))
    for i in range(m):
        for j in range(i, m):
            H[i, j] = H[j, i] = (lagrangian(U0 + E[i] + E[j]) - lagrangian(U0 + E[i] - E[j])
                                 - lagrangian(U0 - E[i] + E[j]) + lagrangian(U0 - E[i] - E[j])) / (4 * step * step)
    h0 = constraint_values(U0)[1]
    active = (h0 >= -gap) & (mu > 0)
    J = np.array([(constraint_values(U0 + E[i])[1] - constraint_values(U0 - E[i])[1]) / (2 * step) for i in range(m)]).T
    Z = null_space(J[active]) if active.any() else np.eye(m)
    return np.linalg.eigvalsh(Z.T @ H @ Z)[0], int(active.sum())


def _merge_with_bounds():
    from solver_cpp import KinematicBicycle
    cost = QuadraticCost(x_ref=(0.0, 1.0, 2.0, 0.0), Q_ref=(0.0, 0.1, 0.01, 1.0), R=(0.3, 0.3))
    lim = dict(u_min=[-1.0, -0.3], u_max=[1.0, 0.3])
    agents = [Agent(KinematicBicycle(1.0, 1.0), [0.0, 1.0, 2.0, 0.0], cost, **lim),
              Agent(KinematicBicycle(1.0, 1.0), [1.0, -1.1, 2.5, 0.0], cost, **lim)]
    return GameProblem(dt=0.2, horizon=10, agents=agents, collision=Collision(2.0, form="squared"))


@pytest.mark.parametrize("case", ["merge3_seed4", "bounds", "pair_distances"])
def test_reduced_hessian_matches_finite_differences(case):
    if case == "bounds":
        problem = _merge_with_bounds()
    else:
        problem = merging_problem(3, 4)
        problem.horizon = 12
    if case == "pair_distances":  # the active pair (0, 1) at its own 2.4 m, another pair with its own 1.7 m
        problem.collision.pair_distances = [PairDistance((0, 1), 2.4), PairDistance((2, 0), [1.7] * 12)]
    result = solve(problem, tol=1e-9, linear=dict(solver="sparse_lu"))
    assert result.status == "converged"
    n_active = 0
    for a in range(problem.num_agents):
        lam_min, na = _fd_reduced_min_eigenvalue(problem, result, a)
        n_active += na
        assert result.second_order[a] == pytest.approx(lam_min, rel=1e-4, abs=1e-5), a
    assert n_active > 0  # the cases exercise the null-space projection


def test_restart_on_saddle_finds_a_local_equilibrium():
    """head-on 2 cars seed 151: the first attempt converges to a saddle (the detection), the restarts kept going
    by restart_on_saddle reach a point that the second-order test accepts and where, independently, SLSQP on
    each player's own problem (others fixed) finds no profitable deviation, while at the saddle it does."""
    from bench.families import family_problem

    problem = family_problem("head-on", 2, 151)
    kept = solve(problem, second_order=dict(restart_on_saddle=False), order=dict(candidates=0))  # the schedule alone
    assert kept.status == "saddle"
    assert max(best_response_gap(problem, kept.x, kept.u, i) for i in range(2)) > 1e-3
    r = solve(problem)  # restart_on_saddle is the default
    assert r.status == "converged" and r.attempts > kept.attempts
    assert np.all(r.second_order > 0)
    assert np.all(stationarity_residual(problem, r.x, r.u, relative=True) <= 1e-3)
    assert max(best_response_gap(problem, r.x, r.u, i) for i in range(2)) <= 1e-4


def test_restart_on_saddle_returns_the_saddle_when_no_attempt_does_better():
    """The disc game (R 1, F 2) from zero controls: every attempt ends at the saddle in front of the discs (its
    minimum is behind the disc, at (1, 0): not reachable by sliding along it), the two escapes along negative
    curvature and the attempt from the best-response guess (each player alone ends at the same saddle) included, so
    after the whole restart schedule the kept saddle is returned, unchanged, with the work of all attempts."""
    problem = _disc_game(1.0, 2.0)
    off = solve(problem, tol=1e-9, second_order=dict(restart_on_saddle=False))
    on = solve(problem, tol=1e-9, restart=dict(count=3))
    assert on.status == "saddle" and on.saddle_escapes == 2 and on.best_response_attempts == 1
    assert on.attempts == 4 + 2 + 1
    assert on.iterations > off.iterations
    np.testing.assert_allclose(on.x[:, 1], [[-1.0, 0.0], [-1.0, 100.0]], atol=1e-6)
    np.testing.assert_allclose(on.second_order, [6 * 1.0 - 4 * 2.0] * 2, rtol=1e-5)


# ------------------------------------------------------------------------------------------------------------
def _slide_game() -> GameProblem:
    """Two single integrators, one step, each with a disc of radius 1 (squared form) in its way, 100 m apart (their
    pair constraint slack). Player 0's cost R |u|^2 + F |p - r|^2 with u = p - (-3, 0), R = (0.5, 0.25),
    F = (1.5, 0.25), r = (1/3, 0) is W |p - c|^2 + const with W = R + F = (2, 0.5) per axis and c = (-1/2, 0)
    inside the disc. On the circle p = (cos t, sin t) its derivative is 2 sin t ((W_y - W_x) cos t + W_x c_x):
    - t = pi, p = (-1, 0): first-order point (multiplier 1) with curvature 2 W_y - 2 = -1 along the circle: a saddle;
    - cos t = W_x c_x / (W_x - W_y) = -2/3, p = (-2/3, +-sqrt(5)/3): the two minima (multiplier 1/2, curvature
      3 * sin^2 t = 5/3 along the circle). Player 1 is the same game shifted by 100 m in y."""
    def agent(y):
        return Agent(LinearModel(np.eye(2), np.eye(2)), (-3.0, y),
                     QuadraticCost(x_ref=(1.0 / 3.0, y), Q_ref=(1.5, 0.25), R=(0.5, 0.25)))
    discs = [Obstacle(np.array([[0.0, y], [0.0, y]]), min_distance=1.0) for y in (0.0, 100.0)]
    return GameProblem(dt=1.0, horizon=1, agents=[agent(0.0), agent(100.0)], collision=Collision(1.0, form="squared"),
                       obstacles=discs)


def test_escape_along_negative_curvature_reaches_the_analytic_minima():
    """From zero controls every attempt converges to the symmetric saddle p = (-1, 0) (eigenvalue -1), which SLSQP
    on each player's own problem improves by ~3.6 %. With saddle_escapes each player moves along its negative
    curvature and Newton from there reaches a minimum p = (-2/3, +-sqrt(5)/3) with eigenvalue 5/3, where SLSQP
    finds no profitable deviation; the escape's iterations are counted."""
    problem = _slide_game()
    kept = solve(problem, tol=1e-9, restart=dict(count=3), second_order=dict(escapes=0))
    assert kept.status == "saddle" and kept.saddle_escapes == 0
    np.testing.assert_allclose(kept.x[:, 1], [[-1.0, 0.0], [-1.0, 100.0]], atol=1e-6)
    np.testing.assert_allclose(kept.second_order, [-1.0, -1.0], rtol=1e-5)
    assert min(best_response_gap(problem, kept.x, kept.u, i) for i in range(2)) > 1e-2

    first = solve(problem, tol=1e-9, second_order=dict(restart_on_saddle=False))
    r = solve(problem, tol=1e-9, restart=dict(count=3), second_order=dict(escapes=1))
    assert r.status == "converged" and r.saddle_escapes == 1 and r.attempts == 2
    assert r.iterations > first.iterations  # the saddle's attempt and the escape, counted together
    np.testing.assert_allclose(np.abs(r.x[:, 1] - [[0.0, 0.0], [0.0, 100.0]]), [[2 / 3, np.sqrt(5) / 3]] * 2, atol=1e-6)
    np.testing.assert_allclose(r.second_order, [5 / 3, 5 / 3], rtol=1e-5)
    assert max(best_response_gap(problem, r.x, r.u, i) for i in range(2)) <= 1e-6
    assert np.all(stationarity_residual(problem, r.x, r.u, relative=True) <= 1e-6)


@pytest.mark.parametrize("cars, seed", [(6, 18), (7, 1)])
def test_escape_holds_the_saddles_nearly_active_contacts(cars, seed):
    """Table I instances whose first attempt converges to a saddle with contacts a hair inside the barrier (within
    barrier.margin). The escape holds those contacts as equalities; left to the barrier-free state the first Newton
    step crossed them and the escape attempt's line search failed at once, returning the saddle. With no restarts
    (attempt 0 and the escapes only), the escape attempt now reaches a point that passes the second-order test, the
    benchmark's stationarity test and, independently, SLSQP's best responses, while the saddle fails the latter."""
    problem = merging_problem(cars, seed)
    saddle = solve(problem, restart=dict(count=0), second_order=dict(restart_on_saddle=False))
    assert saddle.status == "saddle" and saddle.attempts == 1
    assert max(best_response_gap(problem, saddle.x, saddle.u, i) for i in range(cars)) > BEST_RESPONSE_TOL
    r = solve(problem, restart=dict(count=0))
    assert r.status == "converged" and r.saddle_escapes == 1 and r.attempts == 2
    assert np.all(r.second_order > 0)
    assert np.all(stationarity_residual(problem, r.x, r.u, relative=True) <= 1e-3)
    assert max(best_response_gap(problem, r.x, r.u, i) for i in range(cars)) <= BEST_RESPONSE_TOL


def test_inertia_correction_keeps_the_roots():
    """The inertia correction only changes the Newton matrix: on the head-on instance whose first attempt is a
    saddle, the solve with it (and without escapes) still ends at a point that passes the second-order test and,
    independently, SLSQP's best responses."""
    from bench.families import family_problem

    problem = family_problem("head-on", 2, 2)
    r = solve(problem, second_order=dict(escapes=0, inertia=1.5))
    assert r.status == "converged" and r.saddle_escapes == 0
    assert np.all(r.second_order > 0)
    assert np.all(stationarity_residual(problem, r.x, r.u, relative=True) <= 1e-3)
    assert max(best_response_gap(problem, r.x, r.u, i) for i in range(2)) <= 1e-4


def _tridiagonal_cases():
    rng = np.random.default_rng(7)
    yield np.array([3.0]), np.zeros(0)
    yield np.array([1.0, 1.0]), np.array([1.0])  # eigenvalues 0 and 2: a singular matrix
    yield np.full(80, 2.0), np.full(79, -1.0)  # 2 - 2 cos(k pi / 81): the smallest near 0, clustered ends
    for n in (2, 3, 7, 40, 120):
        for scale in (1e-3, 1.0, 1e4):
            d, e = scale * rng.normal(size=n), scale * rng.normal(size=n - 1)
            yield d, e
            e_split = e.copy()
            e_split[::3] = 0.0  # decoupled blocks
            yield d, e_split
            yield np.full(n, scale), scale * 1e-9 * rng.normal(size=n - 1)  # nearly repeated eigenvalues


def test_tridiagonal_extreme_eigenvalues_match_lapack():
    for d, e in _tridiagonal_cases():
        w = np.linalg.eigvalsh(np.diag(d) + np.diag(e, 1) + np.diag(e, -1))
        lo, hi = _core.tridiagonal_extreme_eigenvalues(d, e)
        norm = np.abs(w).max()
        assert abs(lo - w[0]) <= 1e-13 * norm and abs(hi - w[-1]) <= 1e-13 * norm, (len(d), lo, w[0], hi, w[-1])


def test_tridiagonal_extreme_eigenvalues_reject_non_finite():
    assert np.isnan(_core.tridiagonal_extreme_eigenvalues(np.array([1.0, np.nan]), np.array([0.5]))[0])
    with pytest.raises(ValueError, match="length n - 1"):
        _core.tridiagonal_extreme_eigenvalues(np.array([1.0, 2.0]), np.array([0.5, 0.5]))
