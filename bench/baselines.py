"""Baseline game solvers for benchmarks against RD3G: iLQGames (feedback Nash, iterated LQ games) and
ALGames (open-loop Nash, Newton on the augmented-Lagrangian KKT system). Both are C++ (solver_cpp/src/
ilqgames.cpp, algames.cpp) on the same models, derivatives and problem struct as RD3G; see docs/baselines.md.

    python -m app bench baselines        # convergence count and median time on merging seeds 0-19, 2..5 cars
"""
from __future__ import annotations

import argparse

import numpy as np

from bench.merging import merging_problem
from solver_cpp import GameProblem, GameResult, WarmStart, _core, solve
from solver_cpp.solve import fill_settings


def ilqgames_settings(**overrides) -> _core.ILQGamesSettings:
    """C++ defaults (solver_cpp/include/rd3g/ilqgames.hpp) with keyword overrides."""
    return fill_settings(_core.ILQGamesSettings(), "ilqgames", overrides)


def algames_settings(**overrides) -> _core.ALGamesSettings:
    """C++ defaults (solver_cpp/include/rd3g/algames.hpp) with keyword overrides."""
    return fill_settings(_core.ALGamesSettings(), "algames", overrides)


def _warm(problem: GameProblem, warm_start: WarmStart | None) -> _core.WarmStart | None:
    if warm_start is None:
        return None
    N, T, nu = problem.num_agents, int(problem.horizon), problem.agents[0].dynamics.nu
    u = np.asarray(warm_start.u, dtype=float)
    if u.shape != (N, T, nu) or not np.all(np.isfinite(u)):
        raise ValueError(f"warm_start.u must be finite with shape ({N}, {T}, {nu}), got {u.shape}")
    ws = _core.WarmStart()
    ws.u = list(u)
    return ws


def _result(r, constraints) -> GameResult:
    i = r.info
    lam = np.stack(r.lam) if len(r.lam) else np.zeros((0,))
    return GameResult(
        status=_core.status_name(i.status), x=np.stack(r.x), u=np.stack(r.u), lam=lam, mu=np.asarray(r.mu),
        h=np.asarray(r.h), iterations=i.iterations, residual_norm=i.residual_norm, max_violation=i.max_violation,
        residual_history=np.asarray(i.residual_history), solve_time_s=i.timings.total,
        assembly_time_s=i.timings.assembly, linear_solve_time_s=i.timings.linear_solve,
        line_search_time_s=i.timings.line_search, active_constraints=int(np.count_nonzero(np.asarray(r.mu) > 0)),
        symbolic_factorizations=i.symbolic_factorizations, constraints=list(constraints))


def solve_ilqgames(problem: GameProblem, warm_start: WarmStart | None = None, **settings) -> GameResult:
    """Feedback Nash equilibrium by iLQGames. residual_norm is the last iteration's largest state/control
    change; mu holds the penalty multipliers (one per constraint); lam is empty."""
    s = _core.ILQGamesSolver()
    s.setup(problem.to_core(validate=False), ilqgames_settings(**settings))
    return _result(s.solve(_warm(problem, warm_start)), s.constraints())


def solve_algames(problem: GameProblem, warm_start: WarmStart | None = None, **settings) -> GameResult:
    """Open-loop Nash equilibrium by ALGames. residual_norm is ||G||_2 of the augmented-Lagrangian KKT
    system; lam holds the dynamics multipliers (N, T, nx), mu the inequality multipliers."""
    s = _core.ALGamesSolver()
    s.setup(problem.to_core(validate=False), algames_settings(**settings))
    return _result(s.solve(_warm(problem, warm_start)), s.constraints())


def dynamics_defect(problem: GameProblem, result: GameResult) -> float:
    """max |x_{k+1} - f(x_k, u_k)| over agents and steps (state units); x_0 must be the initial state."""
    core = problem.to_core()
    worst = 0.0
    for i, dyn in enumerate(core.dynamics):
        worst = max(worst, float(np.abs(result.x[i, 0] - core.x0[i]).max()))
        for k in range(result.u.shape[1]):
            x_next = dyn.eval(result.x[i, k], result.u[i, k])[0]
            worst = max(worst, float(np.abs(x_next - result.x[i, k + 1]).max()))
    return worst


def min_pair_distance(result: GameResult, pos=(0, 1)) -> float:
    """Smallest distance between any two agents at k = 1..T (m)."""
    p = result.x[:, 1:, list(pos)]  # (N, T, 2)
    d = np.linalg.norm(p[:, None] - p[None, :], axis=-1)  # (N, N, T)
    N = p.shape[0]
    d[np.arange(N), np.arange(N)] = np.inf
    return float(d.min())


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The options of `python -m app bench baselines`."""
    ap.add_argument("--cars", type=int, nargs="+", default=[2, 3, 4, 5])
    ap.add_argument("--seeds", type=int, default=20)


def run(args) -> int:
    """Convergence count, median time and iterations of RD3G and both baselines per car count."""
    solvers = {"rd3g": lambda p: solve(p), "ilqgames": solve_ilqgames, "algames": solve_algames}
    print(f"{'cars':>4} {'solver':>9} {'converged':>9} {'median ms':>10} {'median it':>9}")
    for n in args.cars:
        for name, fn in solvers.items():
            times, its, ok = [], [], 0
            for seed in range(args.seeds):
                r = fn(merging_problem(n, seed))
                ok += r.converged
                if r.converged:
                    times.append(r.solve_time_s * 1e3)
                    its.append(r.iterations)
            med = f"{np.median(times):10.2f}" if times else f"{'-':>10}"
            medi = f"{np.median(its):9.0f}" if its else f"{'-':>9}"
            print(f"{n:>4} {name:>9} {ok:>6}/{args.seeds:<2} {med} {medi}")
    return 0


if __name__ == "__main__":
    raise SystemExit("moved: python -m app bench baselines")
