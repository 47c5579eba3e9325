"""iLQGames and ALGames baselines (bench/baselines.py over solver_cpp/src/ilqgames.cpp, algames.cpp).

References are independent numpy computations: the coupled Riccati recursion of the feedback LQ game
(written from Basar & Olsder), a best-response LQR check of the feedback equilibrium, and the stacked KKT
system of the open-loop LQ game."""
from __future__ import annotations

import numpy as np
import pytest

from bench.baselines import (algames_settings, dynamics_defect, ilqgames_settings, min_pair_distance, solve_algames,
                             solve_ilqgames)
from bench.merging import MIN_DISTANCE, merging_problem
from solver_cpp import Agent, GameProblem, LinearModel, QuadraticCost, _core


# ----------------------------------------------------------------------------------------------- references
def riccati_feedback_game(A, B, dims, Q, l, R, r, QT, lT):
    """Feedback Nash of the LQ game J^i = sum 1/2 x'Q^i x + l^i'x + 1/2 u'R^i u + r^i'u (+ terminal),
    strategies u_k = -P_k x_k - a_k. Player i's condition, block by block:
    sum_j (R^i[i,j] + B_i'Z^i B_j) P_j = B_i'Z^i A and the same with a_j and B_i'z^i + r^i[i]."""
    T, N = len(A), len(dims)
    offs = np.concatenate([[0], np.cumsum(dims)])
    blk = [slice(offs[i], offs[i + 1]) for i in range(N)]
    Z = [QT[i].copy() for i in range(N)]
    z = [lT[i].copy() for i in range(N)]
    P, a = [None] * T, [None] * T
    for k in reversed(range(T)):
        m = offs[-1]
        n = A[k].shape[0]
        S = np.zeros((m, m))
        Yp = np.zeros((m, n))
        Ya = np.zeros(m)
        for i in range(N):
            Bi = B[k][:, blk[i]]
            for j in range(N):
                S[blk[i], blk[j]] = R[k][i][blk[i], blk[j]] + Bi.T @ Z[i] @ B[k][:, blk[j]]
            Yp[blk[i]] = Bi.T @ Z[i] @ A[k]
            Ya[blk[i]] = Bi.T @ z[i] + r[k][i][blk[i]]
        P[k] = np.linalg.solve(S, Yp)
        a[k] = np.linalg.solve(S, Ya)
        F = A[k] - B[k] @ P[k]
        beta = -B[k] @ a[k]
        for i in range(N):
            z[i] = l[k][i] + P[k].T @ (R[k][i] @ a[k] - r[k][i]) + F.T @ (z[i] + Z[i] @ beta)
            Z[i] = Q[k][i] + P[k].T @ R[k][i] @ P[k] + F.T @ Z[i] @ F
    return P, a


def best_response(A, B, dims, Q, l, R, r, QT, lT, P, a, i):
    """Player i's optimal affine feedback when every other player keeps u^j = -P^j x - a^j: a standard
    time-varying LQR with affine dynamics and state-control cross terms. Returns (K_k, kff_k) with
    u^i = -K_k x - kff_k."""
    T = len(A)
    offs = np.concatenate([[0], np.cumsum(dims)])
    bi = slice(offs[i], offs[i + 1])
    m = offs[-1]
    V, v = QT[i].copy(), lT[i].copy()
    K, kff = [None] * T, [None] * T
    for k in reversed(range(T)):
        # joint u = E u^i + G x + g, with the other players' rows of -P, -a.
        E = np.zeros((m, dims[i]))
        E[bi] = np.eye(dims[i])
        G = -P[k].copy()
        g = -a[k].copy()
        G[bi] = 0
        g[bi] = 0
        Ac = A[k] + B[k] @ G
        c = B[k] @ g
        Bc = B[k] @ E
        Rk, rk = R[k][i], r[k][i]
        # stage: 1/2 x'Qx + l'x + 1/2 (Eu+Gx+g)'R(Eu+Gx+g) + r'(Eu+Gx+g); next value 1/2 y'Vy + v'y, y = Ac x + Bc u + c
        Huu = E.T @ Rk @ E + Bc.T @ V @ Bc
        Hux = E.T @ Rk @ G + Bc.T @ V @ Ac
        hu = E.T @ (Rk @ g + rk) + Bc.T @ (V @ c + v)
        K[k] = np.linalg.solve(Huu, Hux)
        kff[k] = np.linalg.solve(Huu, hu)
        # closed loop of player i too, then the value of x
        Gt = G - E @ K[k]
        gt = g - E @ kff[k]
        At = A[k] + B[k] @ Gt
        ct = B[k] @ gt
        v = l[k][i] + Gt.T @ (Rk @ gt + rk) + At.T @ (V @ ct + v)
        V = Q[k][i] + Gt.T @ Rk @ Gt + At.T @ V @ At
    return K, kff


def random_lq_game(rng, n, dims, T):
    N, m = len(dims), sum(dims)
    A = [np.eye(n) + 0.1 * rng.standard_normal((n, n)) for _ in range(T)]
    B = [0.5 * rng.standard_normal((n, m)) for _ in range(T)]

    def psd(d, eps):
        M = rng.standard_normal((d, d))
        return M @ M.T / d + eps * np.eye(d)

    Q = [[psd(n, 0.0) for _ in range(N)] for _ in range(T)]  # coupled: every player weighs the whole state
    l = [[rng.standard_normal(n) for _ in range(N)] for _ in range(T)]
    R = [[psd(m, 0.5) for _ in range(N)] for _ in range(T)]  # cross-control weights included
    r = [[rng.standard_normal(m) for _ in range(N)] for _ in range(T)]
    QT = [psd(n, 0.0) for _ in range(N)]
    lT = [rng.standard_normal(n) for _ in range(N)]
    return A, B, Q, l, R, r, QT, lT


def lq_problem(seed: int, num_players: int, T: int = 12, lead: float = 0.3) -> GameProblem:
    """Unconstrained LQ game expressible by rd3g.Problem: double integrators in the plane, tracking and a
    lead term (progress coupling through the gradient)."""
    rng = np.random.RandomState(seed)
    dt = 0.2
    A1 = np.array([[1, dt], [0, 1]])
    A = np.kron(np.eye(2), A1)
    B = np.kron(np.eye(2), np.array([[0.5 * dt * dt], [dt]]))
    agents = []
    for _ in range(num_players):
        cost = QuadraticCost(x_ref=rng.uniform(-2, 2, 4), Q_ref=rng.uniform(0.1, 1.0, 4), R=rng.uniform(0.1, 1.0, 2),
                             Q=rng.uniform(0.0, 0.2, 4), Qf_ref=rng.uniform(0.5, 2.0, 4))
        agents.append(Agent(dynamics=LinearModel(A=A, B=B), x0=rng.uniform(-3, 3, 4), cost=cost,
                            lead_weight=lead, lead_index=0))
    return GameProblem(dt=dt, horizon=T, agents=agents)


def lq_game_of(problem: GameProblem):
    """The problem's costs in the 1/2-quadratic joint form of riccati_feedback_game (J has no 1/2)."""
    N, T = problem.num_agents, problem.horizon
    Ai = np.asarray(problem.agents[0].dynamics.A, float)
    Bi = np.asarray(problem.agents[0].dynamics.B, float)
    nx, nu = Bi.shape
    n, m = N * nx, N * nu
    Aj = np.kron(np.eye(N), Ai)
    Bj = np.kron(np.eye(N), Bi)
    core = problem.to_core()

    def state_cost(i, terminal):
        c = core.costs[i]
        qr, q = (c.Qf_ref, c.Qf) if terminal else (c.Q_ref, c.Q)
        Qm = np.zeros((n, n))
        lv = np.zeros(n)
        s = slice(i * nx, (i + 1) * nx)
        Qm[s, s] = np.diag(2 * (qr + q))
        lv[s] = -2 * qr * c.x_ref
        w, idx = problem.agents[i].lead_weight, problem.agents[i].lead_index
        for j in range(N):
            lv[j * nx + idx] += -w * (N - 1) if j == i else w
        return Qm, lv

    Q, l, R, r = [], [], [], []
    for k in range(T):
        Qk, lk, Rk, rk = [], [], [], []
        for i in range(N):
            Qm, lv = state_cost(i, False) if k >= 1 else (np.zeros((n, n)), np.zeros(n))
            Rm = np.zeros((m, m))
            Rm[i * nu:(i + 1) * nu, i * nu:(i + 1) * nu] = np.diag(2 * core.costs[i].R)
            Qk.append(Qm), lk.append(lv), Rk.append(Rm), rk.append(np.zeros(m))
        Q.append(Qk), l.append(lk), R.append(Rk), r.append(rk)
    QT, lT = zip(*[state_cost(i, True) for i in range(N)])
    return [Aj] * T, [Bj] * T, [nu] * N, Q, l, R, r, list(QT), list(lT)


def open_loop_kkt(problem: GameProblem):
    """Open-loop Nash of the LQ game: every player's stationarity in its own (u, x) with its dynamics
    multipliers, stacked with all dynamics, solved as one linear system. Returns x (N, T+1, nx), u (N, T, nu)."""
    N, T = problem.num_agents, problem.horizon
    A = np.asarray(problem.agents[0].dynamics.A, float)
    B = np.asarray(problem.agents[0].dynamics.B, float)
    nx, nu = B.shape
    core = problem.to_core()
    per = T * (nu + 2 * nx)  # per player: u_0..u_{T-1}, x_1..x_T, lam_0..lam_{T-1}
    M = np.zeros((N * per, N * per))
    b = np.zeros(N * per)
    for i in range(N):
        o = i * per
        U = lambda k: o + k * nu  # noqa: E731
        X = lambda k: o + T * nu + (k - 1) * nx  # noqa: E731  (k = 1..T)
        L = lambda k: o + T * (nu + nx) + k * nx  # noqa: E731
        c = core.costs[i]
        w, idx = problem.agents[i].lead_weight, problem.agents[i].lead_index
        for k in range(T):
            # d/du_k: 2 R u_k + B' lam_k = 0
            M[U(k):U(k) + nu, U(k):U(k) + nu] = np.diag(2 * c.R)
            M[U(k):U(k) + nu, L(k):L(k) + nx] = B.T
            # dynamics: A x_k + B u_k - x_{k+1} = 0 (x_0 known)
            M[L(k):L(k) + nx, U(k):U(k) + nu] = B
            M[L(k):L(k) + nx, X(k + 1):X(k + 1) + nx] = -np.eye(nx)
            if k >= 1:
                M[L(k):L(k) + nx, X(k):X(k) + nx] = A
            else:
                b[L(k):L(k) + nx] = -A @ np.asarray(problem.agents[i].x0, float)
            # d/dx_{k+1}: cost gradient - lam_k + A' lam_{k+1} = 0
            term = k + 1 == T
            qr, q = (c.Qf_ref, c.Qf) if term else (c.Q_ref, c.Q)
            rows = slice(X(k + 1), X(k + 1) + nx)
            M[rows, X(k + 1):X(k + 1) + nx] = np.diag(2 * (qr + q))
            M[rows, L(k):L(k) + nx] = -np.eye(nx)
            if not term:
                M[rows, L(k + 1):L(k + 1) + nx] = A.T
            b[rows] = 2 * qr * c.x_ref
            b[X(k + 1) + idx] += w * (N - 1)
    sol = np.linalg.solve(M, b)
    x = np.zeros((N, T + 1, nx))
    u = np.zeros((N, T, nu))
    for i in range(N):
        o = i * per
        u[i] = sol[o:o + T * nu].reshape(T, nu)
        x[i, 0] = problem.agents[i].x0
        x[i, 1:] = sol[o + T * nu:o + T * (nu + nx)].reshape(T, nx)
    return x, u


def simulate_feedback(problem: GameProblem, P, a):
    N, T = problem.num_agents, problem.horizon
    A = np.kron(np.eye(N), np.asarray(problem.agents[0].dynamics.A, float))
    B = np.kron(np.eye(N), np.asarray(problem.agents[0].dynamics.B, float))
    nx, nu = problem.agents[0].dynamics.nx, problem.agents[0].dynamics.nu
    xs = [np.concatenate([np.asarray(ag.x0, float) for ag in problem.agents])]
    us = []
    for k in range(T):
        us.append(-P[k] @ xs[-1] - a[k])
        xs.append(A @ xs[-1] + B @ us[-1])
    x = np.stack(xs).reshape(T + 1, N, nx).transpose(1, 0, 2)
    u = np.stack(us).reshape(T, N, nu).transpose(1, 0, 2)
    return x, u


# ----------------------------------------------------------------------------------------------- LQ games
@pytest.mark.parametrize("dims", [(1, 2), (2, 1, 1)])
def test_lq_feedback_game_core_matches_riccati_and_is_a_feedback_nash(dims):
    rng = np.random.default_rng(7 + len(dims))
    n, T = 4, 8
    game = random_lq_game(rng, n, list(dims), T)
    P, a = _core.lq_feedback_game(list(dims), *game)
    P_ref, a_ref = riccati_feedback_game(game[0], game[1], list(dims), *game[2:])
    for k in range(T):
        np.testing.assert_allclose(P[k], P_ref[k], atol=1e-9, rtol=1e-9)
        np.testing.assert_allclose(a[k], a_ref[k], atol=1e-9, rtol=1e-9)
    # Equilibrium property: no player can improve by changing its own feedback law.
    offs = np.concatenate([[0], np.cumsum(dims)])
    for i in range(len(dims)):
        K, kff = best_response(game[0], game[1], list(dims), *game[2:], P, a, i)
        for k in range(T):
            np.testing.assert_allclose(K[k], P[k][offs[i]:offs[i + 1]], atol=1e-8)
            np.testing.assert_allclose(kff[k], a[k][offs[i]:offs[i + 1]], atol=1e-8)


def test_lq_feedback_game_rejects_bad_shapes():
    rng = np.random.default_rng(0)
    game = list(random_lq_game(rng, 3, [1, 1], 4))
    game[1] = [Bk[:, :1] for Bk in game[1]]
    with pytest.raises(ValueError, match=r"B\[0\]"):
        _core.lq_feedback_game([1, 1], *game)


@pytest.mark.parametrize("num_players,seed", [(2, 0), (3, 1)])
def test_ilqgames_matches_feedback_riccati_on_lq_game(num_players, seed):
    problem = lq_problem(seed, num_players)
    # Trust region off: the LQ approximation is exact, so one full step lands on the equilibrium.
    res = solve_ilqgames(problem, tol=1e-10, max_state_change=1e6)
    assert res.status == "converged"
    assert res.iterations == 1
    A, B, dims, *costs = lq_game_of(problem)
    P, a = riccati_feedback_game(A, B, dims, *costs)
    x_ref, u_ref = simulate_feedback(problem, P, a)
    np.testing.assert_allclose(res.u, u_ref, atol=1e-6)
    np.testing.assert_allclose(res.x, x_ref, atol=1e-6)


@pytest.mark.parametrize("num_players,seed", [(2, 2), (3, 3)])
def test_algames_matches_open_loop_kkt_on_lq_game(num_players, seed):
    problem = lq_problem(seed, num_players)
    res = solve_algames(problem, tol=1e-10)
    assert res.status == "converged"
    x_ref, u_ref = open_loop_kkt(problem)
    np.testing.assert_allclose(res.u, u_ref, atol=1e-6)
    np.testing.assert_allclose(res.x, x_ref, atol=1e-6)
    # Quadratic costs coupled only through the (linear) lead term: no player's gains see the others'
    # states, so feedback and open-loop equilibria coincide here and iLQGames lands on the same point.
    fb = solve_ilqgames(problem, tol=1e-10)
    np.testing.assert_allclose(fb.u, u_ref, atol=1e-6)


# ----------------------------------------------------------------------------------------------- merging
@pytest.mark.parametrize("num_cars,seed", [(2, 0), (2, 3), (3, 1), (3, 4)])
@pytest.mark.parametrize("solver", [solve_ilqgames, solve_algames])
def test_baselines_solve_merging(solver, num_cars, seed):
    problem = merging_problem(num_cars, seed)
    res = solver(problem)
    assert res.status == "converged", (res.status, res.iterations, res.residual_norm, res.max_violation)
    assert res.x.shape == (num_cars, problem.horizon + 1, 4) and res.u.shape == (num_cars, problem.horizon, 2)
    assert dynamics_defect(problem, res) < 1e-6
    assert min_pair_distance(res) > MIN_DISTANCE - 1e-3
    # The independent check of the reported violation: squared form h = d_min^2 - |p_i - p_j|^2.
    assert res.max_violation <= 1e-4 + 1e-12
    # Every car makes progress and ends near the reference lane.
    assert np.all(res.x[:, -1, 0] > res.x[:, 0, 0])
    assert np.all(np.abs(res.x[:, -1, 1] - 1.0) < 0.5)


def test_settings_are_validated():
    with pytest.raises(ValueError, match="ilqgames.nonsense"):
        ilqgames_settings(nonsense=1)
    with pytest.raises(ValueError, match="algames.max_iter"):
        algames_settings(max_iter=2.5)
    with pytest.raises(ValueError, match="ALGamesSettings out of range"):
        solve_algames(merging_problem(2, 0), ls_beta=1.5)
    with pytest.raises(ValueError, match="ILQGamesSettings out of range"):
        solve_ilqgames(merging_problem(2, 0), tol=0.0)
