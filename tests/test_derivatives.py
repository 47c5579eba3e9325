"""Analytic derivatives of the C++ core against central finite differences.

1. Every dynamics model: A = df/dx, B = df/du and lambda_hessian = d2(lam'f)/d[x;u]2.
2. The solver's Newton system: the residual r (stationarity rows, dynamics rows, constraint rows) against
   finite differences of each player's Lagrangian written here from the problem definition, and the
   dense Jacobian J against finite differences of r, for both barrier modes and both collision forms,
   with bounds, an obstacle and three distinct pair distances (the default, a per-pair number and a per-pair
   per-step list), with and without a per-step scale of the first position coordinate (Collision.pos_x_scale:
   an ellipse), at points where some constraints are violated and some satisfied.
"""
import numpy as np
import pytest

from bench.verify import player_cost
from solver_cpp import (Agent, Collision, GameProblem, KinematicBicycle, KinematicBicycleFrenet, LinearModel,
                        Obstacle, PairDistance, QuadraticCost, Solver)

EPS = 1e-6


def _central_diff(fun, z, eps=EPS):
    """Jacobian of fun (vector -> vector or scalar) at z by central differences, columns = dz."""
    cols = []
    for q in range(z.size):
        dz = np.zeros_like(z)
        dz[q] = eps
        cols.append((np.atleast_1d(fun(z + dz)) - np.atleast_1d(fun(z - dz))) / (2 * eps))
    return np.stack(cols, axis=-1)


def _models(rng):
    """(name, built dynamics, sampler of (x, u)) for every C++ model."""
    kappa = 0.3 * rng.standard_normal(12)  # nontrivial curvature table, 12 samples every 0.7 m
    ds = 0.7

    def bicycle_point():
        return (np.array([*rng.normal(0, 3, 2), rng.uniform(0.5, 3.0), rng.uniform(-np.pi, np.pi)]),
                np.array([rng.normal(0, 1), rng.uniform(-0.5, 0.5)]))

    def frenet_point(s_lo, s_hi):
        def sample():
            while True:  # stay off the table's cell boundaries (kappa is only piecewise linear)
                s = rng.uniform(s_lo, s_hi)
                if 0.01 < (s / ds) % 1.0 < 0.99:
                    break
            return (np.array([s, rng.uniform(-0.5, 0.5), rng.uniform(0.5, 3.0), rng.uniform(-0.6, 0.6)]),
                    np.array([rng.normal(0, 1), rng.uniform(-0.5, 0.5)]))
        return sample

    A = rng.normal(size=(3, 3))
    B = rng.normal(size=(3, 2))
    length = kappa.size * ds
    return [
        ("kinematic_bicycle", KinematicBicycle(lf=0.9, lr=1.1).build(0.1), bicycle_point),
        # closed: s beyond one lap and negative s exercise the periodic wrap
        ("frenet_closed", KinematicBicycleFrenet(0.9, 1.1, kappa, ds, closed=True).build(0.1),
         frenet_point(-length, 2.5 * length)),
        # open: inside the table and beyond both ends (constant extrapolation)
        ("frenet_open", KinematicBicycleFrenet(0.9, 1.1, kappa, ds, closed=False).build(0.1),
         frenet_point(-2.0, (kappa.size - 1) * ds + 2.0)),
        ("linear", LinearModel(A, B).build(0.1),
         lambda: (rng.normal(size=3), rng.normal(size=2))),
    ]


def test_dynamics_models_match_finite_differences():
    rng = np.random.default_rng(7)
    for name, f, sample in _models(rng):
        nx, nu = f.nx, f.nu
        for _ in range(25):
            x, u = sample()
            lam = rng.normal(size=nx)
            _, A, B = f.eval(x, u)
            A_fd = _central_diff(lambda xx: f.eval(xx, u)[0], x)
            B_fd = _central_diff(lambda uu: f.eval(x, uu)[0], u)
            np.testing.assert_allclose(A, A_fd, atol=1e-7, rtol=1e-6, err_msg=f"{name}: A at x={x}, u={u}")
            np.testing.assert_allclose(B, B_fd, atol=1e-7, rtol=1e-6, err_msg=f"{name}: B at x={x}, u={u}")

            # d/d[x;u] of the gradient [A'lam; B'lam] is the Hessian of lam'f.
            def grad_lam_f(z):
                _, Az, Bz = f.eval(z[:nx], z[nx:])
                return np.concatenate([Az.T @ lam, Bz.T @ lam])

            H = f.lambda_hessian(x, u, lam)
            H_fd = _central_diff(grad_lam_f, np.concatenate([x, u]))
            np.testing.assert_allclose(H, H_fd, atol=1e-6, rtol=1e-5, err_msg=f"{name}: lambda_hessian at x={x}, u={u}")
            np.testing.assert_allclose(H, H.T, atol=1e-12, err_msg=f"{name}: lambda_hessian not symmetric")


def test_derivative_patterns_hold_every_nonzero_derivative():
    """Outside a model's declared pattern the finite-difference derivatives are zero at every sampled point (the
    Newton matrix holds only the pattern's entries); the bicycle's pattern is the sparse one its equations give."""
    rng = np.random.default_rng(11)
    models = _models(rng)
    A_lin = np.array([[1.0, 0.0, 0.1], [0.0, 1.0, 0.0], [0.2, 0.0, 1.0]])
    models.append(("linear_sparse", LinearModel(A_lin, np.array([[0.0, 1.0], [0.5, 0.0], [0.0, 0.0]])).build(0.1),
                   lambda: (rng.normal(size=3), rng.normal(size=2))))
    for name, f, sample in models:
        nx = f.nx
        PA, PB, PH = (np.asarray(p, dtype=bool) for p in f.derivative_pattern())
        for _ in range(25):
            x, u = sample()
            lam = rng.normal(size=nx)
            A_fd = _central_diff(lambda xx: f.eval(xx, u)[0], x)
            B_fd = _central_diff(lambda uu: f.eval(x, uu)[0], u)

            def grad_lam_f(z):
                _, Az, Bz = f.eval(z[:nx], z[nx:])
                return np.concatenate([Az.T @ lam, Bz.T @ lam])

            H_fd = _central_diff(grad_lam_f, np.concatenate([x, u]))
            for label, fd, pattern in (("A", A_fd, PA), ("B", B_fd, PB), ("H", H_fd, PH)):
                assert np.all(np.abs(fd[~pattern]) <= 1e-9), f"{name}: {label} nonzero outside its pattern at x={x}, u={u}"
    bicycle = KinematicBicycle(lf=0.9, lr=1.1).build(0.1)
    PA, PB, PH = (np.asarray(p, dtype=bool) for p in bicycle.derivative_pattern())
    # px' = px + dt v cos(theta + beta), py' = py + dt v sin(.), v' = v + dt a, theta' = theta + dt v sin(beta) / lr
    assert PA.sum() == 9 and PB.sum() == 4 and PH.sum() == 8
    assert not PH[2, 2] and PH[5, 5] and PB[2, 0] and not PB[2, 1]


# ------------------------------------------------------------------------------------------------
# Residual and Newton matrix of the solver
T_RES = 4
RHO = 0.05
MARGIN = 1e-4  # Settings.barrier_margin default: constraints with -margin <= h < 0 are left out


def _residual_problem(form: str, rng, pos_x_scale=None) -> GameProblem:
    agents = []
    for i in range(3):
        cost = QuadraticCost(x_ref=[0.0, 1.0, 2.0, 0.0], Q_ref=rng.uniform(0.1, 1.0, 4), R=rng.uniform(0.1, 1.0, 2),
                             Q=rng.uniform(0.0, 0.2, 4), Qf_ref=rng.uniform(0.5, 2.0, 4), Qf=rng.uniform(0.0, 0.2, 4))
        agents.append(Agent(dynamics=KinematicBicycle(lf=1.0, lr=1.0), x0=[2.0 * i, 0.3 * i, 2.0, 0.1], cost=cost,
                            u_min=[-1.0, -0.4], u_max=[1.0, 0.4], x_min=[-np.inf, -1.5, 0.5, -np.inf],
                            x_max=[np.inf, 2.5, 2.5, np.inf], lead_weight=0.3 * (i + 1), lead_index=0))
    obstacle = Obstacle(positions=np.column_stack([np.linspace(1.0, 4.0, T_RES + 1), np.full(T_RES + 1, 0.5)]),
                        min_distance=1.2)
    # Pair (0, 1) keeps the default distance; (2, 0) and (1, 2) have their own, the second one per step.
    pairs = [PairDistance(agents=(2, 0), min_distance=1.4),
             PairDistance(agents=(1, 2), min_distance=np.linspace(1.7, 2.6, T_RES))]
    return GameProblem(dt=0.2, horizon=T_RES, agents=agents,
                       collision=Collision(min_distance=2.0, form=form, pair_distances=pairs, pos_x_scale=pos_x_scale),
                       obstacles=[obstacle])


def _constraint_values(problem: GameProblem, constraints, x, u, form):
    """h of every constraint in the solver's order (its constraint list names kind, agents, step,
    component), written from the problem definition. Returns [(h, involved players)]."""
    T = problem.horizon
    d_pair = {frozenset(q.agents): np.broadcast_to(q.min_distance, (T,)) for q in problem.collision.pair_distances}
    d_default = np.broadcast_to(problem.collision.min_distance, (T,))

    scale = np.ones(T) if problem.collision.pos_x_scale is None else np.asarray(problem.collision.pos_x_scale)

    def dist_h(d, dmin, k):
        d = np.array([scale[k - 1] * d[0], d[1]])  # the ellipse: the first coordinate scaled at step k
        return dmin - np.linalg.norm(d) if form == "distance" else dmin ** 2 - d @ d

    out = []
    for c in constraints:
        kind = c.kind.name
        a = problem.agents[c.i]
        if kind == "pair":
            d_min = d_pair.get(frozenset((c.i, c.j)), d_default)[c.k - 1]
            out.append((dist_h(x[c.i, c.k, :2] - x[c.j, c.k, :2], d_min, c.k), (c.i, c.j)))
        elif kind == "obstacle":
            o = problem.obstacles[c.j]
            out.append((dist_h(x[c.i, c.k, :2] - o.positions[c.k], o.min_distance, c.k), (c.i,)))
        elif kind == "state_max":
            out.append((x[c.i, c.k, c.idx] - a.x_max[c.idx], (c.i,)))
        elif kind == "state_min":
            out.append((a.x_min[c.idx] - x[c.i, c.k, c.idx], (c.i,)))
        elif kind == "control_max":
            out.append((u[c.i, c.k, c.idx] - a.u_max[c.idx], (c.i,)))
        else:
            out.append((a.u_min[c.idx] - u[c.i, c.k, c.idx], (c.i,)))
    return out


def _lagrangian(problem, constraints, x, u, lam, mu, i, form, barrier, partition):
    """Player i's Lagrangian: J^i + sum_k lam_k'(f(x_k,u_k) - x_{k+1}) + sum over active constraints
    involving i of mu h + (primal barrier mode) -rho log(-h) over barrier constraints involving i."""
    f = problem.agents[i].dynamics.build(problem.dt)
    L = player_cost(problem, x, u, i)
    for k in range(problem.horizon):
        L += lam[i, k] @ (f.eval(x[i, k], u[i, k])[0] - x[i, k + 1])
    for c, (h, who) in enumerate(_constraint_values(problem, constraints, x, u, form)):
        if i not in who:
            continue
        if partition[c] == "active":
            L += mu[c] * h
        elif partition[c] == "barrier" and barrier == "primal":
            L += -RHO * np.log(-h)
    return L


def _random_point(problem, constraints, rng):
    """A primal-dual point with cars and the obstacle bunched together, so that some collision and bound
    constraints are violated and others satisfied; rerolled until no constraint sits near a partition
    boundary (h = 0 or h = -barrier_margin), where finite differences would cross it."""
    N, T = problem.num_agents, problem.horizon
    while True:
        x = np.empty((N, T + 1, 4))
        x[:, :, 0] = np.linspace(1.0, 4.0, T + 1) + rng.normal(0, 1.2, (N, T + 1))
        x[:, :, 1] = rng.normal(0.5, 1.2, (N, T + 1))
        x[:, :, 2] = rng.uniform(0.2, 2.8, (N, T + 1))
        x[:, :, 3] = rng.normal(0, 0.4, (N, T + 1))
        x[:, 0] = [a.x0 for a in problem.agents]
        u = rng.normal(0, 0.8, (N, T, 2))
        lam = rng.normal(size=(N, T, 4))
        h = np.array([v for v, _ in _constraint_values(problem, constraints, x, u, problem.collision.form)])
        if np.min(np.abs(h)) > 1e-3 and np.min(np.abs(h + MARGIN)) > 1e-3:
            mu = np.abs(rng.normal(size=h.size))
            return x, u, lam, mu, h


@pytest.mark.parametrize("barrier, form, pos_x_scale", [
    ("primal", "distance", None), ("primal_dual", "distance", None), ("primal", "squared", None),
    ("primal_dual", "squared", None), ("primal", "distance", [0.4, 0.7, 1.0, 1.3]),
    ("primal_dual", "squared", [1.5, 0.5, 0.8, 0.3])])
def test_newton_residual_and_jacobian_match_finite_differences(barrier, form, pos_x_scale):
    rng = np.random.default_rng(11 if form == "distance" else 12)
    problem = _residual_problem(form, rng, pos_x_scale)
    solver = Solver(problem, barrier=dict(mode=barrier))
    core = solver._solver
    constraints = core.constraints()
    kinds = [c.kind.name for c in constraints]
    x, u, lam, mu, h = _random_point(problem, constraints, rng)
    N, T = problem.num_agents, problem.horizon

    def residual(x_, u_, lam_, mu_):
        r, _, cols_ = core.debug_residual(list(x_), list(u_), list(lam_), mu_, RHO)
        assert list(cols_) == list(cols), "partition changed under a finite-difference step"
        return r

    r, J, cols = core.debug_residual(list(x), list(u), list(lam), mu, RHO)
    cols = np.asarray(cols)
    partition = np.where(h >= 0, "active", np.where(h < -MARGIN, "barrier", "free"))
    # The partition debug_residual reports is the documented first-iteration one.
    np.testing.assert_array_equal(cols >= 0, partition == "active")
    # Every constraint type is represented both violated (active) and satisfied (barrier).
    for kind in ("pair", "obstacle", "state_max", "state_min", "control_max", "control_min"):
        of_kind = np.array(kinds) == kind
        assert np.any(of_kind & (partition == "active")), f"no violated {kind} constraint at the test point"
        assert np.any(of_kind & (partition == "barrier")), f"no satisfied {kind} constraint at the test point"

    # r against an independent Lagrangian: stationarity rows are FD gradients of player i's
    # Lagrangian wrt its own u_k and x_{k+1}; dynamics rows are f - x_{k+1}; multiplier rows are h.
    # (Primal-dual mode: debug_residual starts the barrier duals z at 0, so barrier terms enter neither r
    # nor J there; the log barrier itself is covered by the primal mode.)
    for i in range(N):
        f = problem.agents[i].dynamics.build(problem.dt)
        for k in range(T):
            def L_of_u(v, k=k, i=i):
                u2 = u.copy()
                u2[i, k] = v
                return _lagrangian(problem, constraints, x, u2, lam, mu, i, form, barrier, partition)

            def L_of_x(v, k=k, i=i):
                x2 = x.copy()
                x2[i, k + 1] = v
                return _lagrangian(problem, constraints, x2, u, lam, mu, i, form, barrier, partition)

            cu, cl, cx = core.column_of(i, k, 0), core.column_of(i, k, 1), core.column_of(i, k, 2)
            np.testing.assert_allclose(r[cu:cu + 2], _central_diff(L_of_u, u[i, k].copy()).ravel(), atol=1e-6,
                                       err_msg=f"dL/du row, agent {i}, k {k}")
            np.testing.assert_allclose(r[cx:cx + 4], _central_diff(L_of_x, x[i, k + 1].copy()).ravel(), atol=1e-6,
                                       err_msg=f"dL/dx row, agent {i}, k {k + 1}")
            np.testing.assert_allclose(r[cl:cl + 4], f.eval(x[i, k], u[i, k])[0] - x[i, k + 1], atol=1e-12)
    active = np.flatnonzero(cols >= 0)
    np.testing.assert_allclose(r[cols[active]], h[active], atol=1e-12)

    # J against finite differences of r, column by column.
    J_fd = np.zeros_like(J)
    for i in range(N):
        for k in range(T):
            for kind, arr, dim, step in ((0, u, 2, k), (1, lam, 4, k), (2, x, 4, k + 1)):
                c0 = core.column_of(i, k, kind)
                for d in range(dim):
                    def r_of(v, i=i, step=step, d=d, kind=kind, arr=arr):
                        a2 = arr.copy()
                        a2[i, step, d] = v[0]
                        args = {0: (x, a2, lam, mu), 1: (x, u, a2, mu), 2: (a2, u, lam, mu)}[kind]
                        return residual(*args)
                    J_fd[:, c0 + d] = _central_diff(r_of, np.array([arr[i, step, d]]))[:, 0]
    for c in active:
        def r_of_mu(v, c=c):
            m2 = mu.copy()
            m2[c] = v[0]
            return residual(x, u, lam, m2)
        J_fd[:, cols[c]] = _central_diff(r_of_mu, np.array([mu[c]]))[:, 0]
    scale = np.abs(J).max()
    err = np.abs(J - J_fd)
    where = np.unravel_index(err.argmax(), err.shape)
    assert err.max() < 1e-6 * scale, f"J differs from FD of r by {err.max():.3e} at {where} (scale {scale:.2f})"
