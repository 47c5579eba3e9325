"""Initial guess for a game from a few rounds of iterated best response: each agent in turn solves its own
problem (the same C++ solver, one agent) with the others' current plans as moving obstacles."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .problem import GameProblem, Obstacle
from .solve import WarmStart, solve


def best_response_guess(problem: GameProblem, rounds: int = 2, **settings) -> WarmStart:
    """Controls (N, T, nu) after `rounds` Gauss-Seidel sweeps, starting from zero controls. Each single-agent solve
    avoids the others' latest rolled-out positions at the game's collision distance (an agent whose solve fails
    keeps the controls it returned, which satisfy its dynamics). Settings go to every single-agent solve."""
    if rounds < 1:
        raise ValueError(f"rounds must be at least 1, got {rounds}")
    N, T = problem.num_agents, int(problem.horizon)
    nu = problem.agents[0].dynamics.nu
    col = problem.collision
    u = np.zeros((N, T, nu))
    x = problem.rollout(u)
    px, py = (col.pos_x, col.pos_y) if col is not None else (0, 1)
    for _ in range(rounds):
        for i, agent in enumerate(problem.agents):
            obstacles = list(problem.obstacles)
            if col is not None and col.enabled:
                obstacles += [Obstacle(x[j][:, [px, py]], col.min_distance) for j in range(N) if j != i]
            single = GameProblem(dt=problem.dt, horizon=T, agents=[agent], collision=replace(col, enabled=False)
                                 if col is not None else None, obstacles=obstacles)
            r = solve(single, **settings)
            if np.all(np.isfinite(r.u)) and np.all(np.isfinite(r.x)):
                u[i], x[i] = r.u[0], r.x[0]
    return WarmStart(u=u)
