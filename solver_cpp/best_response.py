"""Initial guess for a game from a few rounds of iterated best response: each agent in turn solves its own
problem (the same C++ solver, one agent) with the others' current plans as moving obstacles. The sweeps are the
C++ solver's own (solver_cpp/src/best_response.cpp), those of its best-response restart (setting
best_response.rounds, docs/solver.md)."""
from __future__ import annotations

from .problem import GameProblem
from .solve import Solver, WarmStart


def best_response_guess(problem: GameProblem, rounds: int = 2, warm_start: WarmStart | None = None,
                        **settings) -> WarmStart:
    """Controls (N, T, nu) after `rounds` Gauss-Seidel sweeps from the warm start's controls (zero without). Each
    single-agent solve starts from its agent's current controls and avoids the others' latest rolled-out positions
    at the game's collision distance; an agent whose solve fails keeps the controls it returned if finite. Settings
    are the game's (as for solver_cpp.solve): each single-agent solve gets them with at most best_response.max_iter
    iterations and best_response.restarts restarts (default 0: a solve that stalls returns its controls as they are;
    1 gives a stalled solve a second attempt), and all of them together at most max_iter."""
    if rounds < 1:
        raise ValueError(f"rounds must be at least 1, got {rounds}")
    return Solver(problem, **settings).best_response(rounds, warm_start)
