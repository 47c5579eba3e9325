"""Unconstrained linear-quadratic games: the solver against the open-loop Nash equilibrium computed here
from the stacked KKT conditions of all players (written from the cost definition in
solver_cpp.QuadraticCost, no 1/2 factor, and the lead term of solver_cpp.Agent).

Player i minimises over (u^i, x^i)
    J^i = sum_{k<T} u_k'R u_k + sum_{1<=k<T} [(x_k-r)'Q_r(x_k-r) + x_k'Q x_k] + (x_T-r)'F_r(x_T-r) + x_T'F x_T
          + w_i sum_{k=1..T} sum_{j!=i} (x^j_k[l] - x^i_k[l])
subject to x^i_{k+1} = A_i x^i_k + B_i u^i_k. With multipliers lam_k of the dynamics, its conditions are
    2 R u_k + B' lam_k = 0,                                                  k = 0..T-1
    2 (Q_r + Q) x_k - 2 Q_r r - w_i (N-1) e_l + A' lam_k - lam_{k-1} = 0,   k = 1..T-1
    2 (F_r + F) x_T - 2 F_r r - w_i (N-1) e_l - lam_{T-1} = 0
    A x_k + B u_k - x_{k+1} = 0.
The lead term is the only coupling the cost API offers; being linear in the other players' states it
drops out of player i's conditions except for its own constant gradient -w_i (N-1) e_l, so the stacked
system is block diagonal (checked below) and the lead weights shift every player's equilibrium.
"""
import numpy as np
import pytest

from bench.verify import player_cost
from solver_cpp import Agent, GameProblem, LinearModel, QuadraticCost, solve

TOL = 1e-9


def _random_game(num_players: int, seed: int, nx: int = 3, nu: int = 2, horizon: int = 12) -> GameProblem:
    rng = np.random.default_rng(seed)
    agents = []
    for i in range(num_players):
        A = rng.normal(size=(nx, nx))
        A *= rng.uniform(0.6, 0.95) / np.max(np.abs(np.linalg.eigvals(A)))  # stable
        B = rng.normal(size=(nx, nu))
        cost = QuadraticCost(x_ref=rng.normal(size=nx), Q_ref=rng.uniform(0.2, 2.0, nx), R=rng.uniform(0.1, 1.0, nu),
                             Q=rng.uniform(0.0, 0.5, nx), Qf_ref=rng.uniform(1.0, 5.0, nx), Qf=rng.uniform(0.0, 0.5, nx))
        agents.append(Agent(dynamics=LinearModel(A, B), x0=rng.normal(size=nx), cost=cost,
                            lead_weight=rng.uniform(0.2, 1.0), lead_index=int(rng.integers(nx))))
    return GameProblem(dt=0.1, horizon=horizon, agents=agents, collision=None)


def _nash_kkt(problem: GameProblem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve the stacked KKT system of all players. Returns (x (N, T+1, nx), u (N, T, nu), K)."""
    N, T = problem.num_agents, problem.horizon
    nx, nu = problem.agents[0].dynamics.nx, problem.agents[0].dynamics.nu
    n_i = T * (nu + nx + nx)  # per player: u_0..u_{T-1}, x_1..x_T, lam_0..lam_{T-1}
    iu = lambda i, k: i * n_i + k * nu  # noqa: E731
    ix = lambda i, k: i * n_i + T * nu + (k - 1) * nx  # noqa: E731  (k = 1..T)
    il = lambda i, k: i * n_i + T * (nu + nx) + k * nx  # noqa: E731
    K = np.zeros((N * n_i, N * n_i))
    rhs = np.zeros(N * n_i)
    I = np.eye(nx)
    for i, a in enumerate(problem.agents):
        A, B = np.asarray(a.dynamics.A), np.asarray(a.dynamics.B)
        c = a.cost
        R, r = np.diag(c.R), np.asarray(c.x_ref)
        lead = np.zeros(nx)
        lead[a.lead_index] = a.lead_weight * (N - 1)
        for k in range(T):
            # stationarity in u_k (rows indexed like the variable)
            K[iu(i, k):iu(i, k) + nu, iu(i, k):iu(i, k) + nu] = 2 * R
            K[iu(i, k):iu(i, k) + nu, il(i, k):il(i, k) + nx] = B.T
            # stationarity in x_{k+1}
            row = ix(i, k + 1)
            terminal = k + 1 == T
            Wr, W = (np.diag(c.Qf_ref), np.diag(c.Qf)) if terminal else (np.diag(c.Q_ref), np.diag(c.Q))
            K[row:row + nx, row:row + nx] = 2 * (Wr + W)
            K[row:row + nx, il(i, k):il(i, k) + nx] = -I
            if not terminal:
                K[row:row + nx, il(i, k + 1):il(i, k + 1) + nx] = A.T
            rhs[row:row + nx] = 2 * Wr @ r + lead
            # dynamics A x_k + B u_k - x_{k+1} = 0 (x_0 known: moves to the right-hand side)
            rl = il(i, k)
            K[rl:rl + nx, iu(i, k):iu(i, k) + nu] = B
            K[rl:rl + nx, ix(i, k + 1):ix(i, k + 1) + nx] = -I
            if k == 0:
                rhs[rl:rl + nx] = -A @ np.asarray(a.x0, dtype=float)
            else:
                K[rl:rl + nx, ix(i, k):ix(i, k) + nx] = A
    sol = np.linalg.solve(K, rhs)
    x = np.zeros((N, T + 1, nx))
    u = np.zeros((N, T, nu))
    for i, a in enumerate(problem.agents):
        x[i, 0] = a.x0
        for k in range(T):
            u[i, k] = sol[iu(i, k):iu(i, k) + nu]
            x[i, k + 1] = sol[ix(i, k + 1):ix(i, k + 1) + nx]
    return x, u, K


@pytest.mark.parametrize("num_players, seed", [(2, 0), (3, 1), (4, 2)])
def test_lq_game_matches_stacked_kkt_and_newton_converges_in_one_step(num_players, seed):
    problem = _random_game(num_players, seed)
    x_ref, u_ref, K = _nash_kkt(problem)

    # The reference is a Nash equilibrium: each player's cost is a strictly convex quadratic of its
    # own controls, so no unilateral control change lowers it (probe random directions).
    rng = np.random.default_rng(seed)
    for i, a in enumerate(problem.agents):
        f = a.dynamics.build(problem.dt)
        J_star = player_cost(problem, x_ref, u_ref, i)
        for _ in range(5):
            u2 = u_ref.copy()
            u2[i] += 1e-3 * rng.normal(size=u2[i].shape)
            x2 = x_ref.copy()
            x2[i] = f.rollout(x_ref[i, 0], u2[i])
            assert player_cost(problem, x2, u2, i) > J_star
    n_i = K.shape[0] // num_players
    off_diagonal = K.copy()
    for i in range(num_players):
        off_diagonal[i * n_i:(i + 1) * n_i, i * n_i:(i + 1) * n_i] = 0
    assert not off_diagonal.any()  # see the module docstring

    # rho_init = tol/10 skips the barrier-weight schedule, which has nothing to act on here (no
    # inequality constraints); see test_unconstrained_game_converges_with_default_barrier_schedule.
    result = solve(problem, tol=TOL, restart=dict(count=0), barrier=dict(rho_init=TOL / 10))
    assert result.status == "converged"
    assert result.iterations <= 2
    np.testing.assert_allclose(result.x, x_ref, atol=1e-6, rtol=0)
    np.testing.assert_allclose(result.u, u_ref, atol=1e-6, rtol=0)
    # Newton on a linear KKT system: one step lands on the solution whatever the barrier weight.
    default = solve(problem, tol=TOL, restart=dict(count=0))
    assert default.residual_history[1] < TOL
    np.testing.assert_allclose(default.u, u_ref, atol=1e-6, rtol=0)


def test_lead_weight_changes_the_equilibrium():
    """The lead term matters: without it the equilibrium differs (both match their own reference)."""
    problem = _random_game(3, 5)
    x_lead, u_lead, _ = _nash_kkt(problem)
    for a in problem.agents:
        a.lead_weight = 0.0
    x_none, u_none, _ = _nash_kkt(problem)
    assert np.abs(u_lead - u_none).max() > 1e-2
    result = solve(problem, tol=TOL, restart=dict(count=0), barrier=dict(rho_init=TOL / 10))
    np.testing.assert_allclose(result.u, u_none, atol=1e-6, rtol=0)


def test_unconstrained_game_converges_with_default_barrier_schedule():
    problem = _random_game(3, 1)
    result = solve(problem, tol=TOL, restart=dict(count=0))
    assert result.status == "converged"
    assert result.iterations <= 2
