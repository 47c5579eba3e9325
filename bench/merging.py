"""The car-merging game of the RD3G paper, with the constants of the authors' public benchmark
(documented in docs/merging.md)."""
from __future__ import annotations

import numpy as np

from solver_cpp import Agent, Collision, GameProblem, KinematicBicycle, QuadraticCost

DT = 0.2  # s
HORIZON = 20
LF = LR = 1.0  # m
MAIN_LANE_Y = 1.1  # m, left lane (cars merge into it)
MERGE_LANE_Y = -1.1  # m
Y_REF = 1.0  # m, lateral reference of every car (as in the authors' code)
V_REF = 2.0  # m/s
Q_REF = (0.0, 0.1, 0.01, 1.0)
R = (0.3, 0.3)
MIN_DISTANCE = 2.0  # m, collision radius, squared form
CAR_SPACING = 5.4  # m


def lane_counts(num_cars: int) -> tuple[int, int]:
    """(main-lane cars, merging-lane cars): floor(N/2) in the main lane, at most N-1."""
    if num_cars < 2:
        raise ValueError(f"cars must be at least 2, got {num_cars}")
    n_main = min(num_cars // 2, num_cars - 1)
    return n_main, num_cars - n_main


def initial_states(num_cars: int, seed: int, spacing: float = CAR_SPACING, main_lane_y: float = MAIN_LANE_Y,
                   merge_lane_y: float = MERGE_LANE_Y) -> np.ndarray:
    """(N, 4) initial states [x, y, v, theta]; main-lane cars first, then merging-lane cars (the other families
    in bench/families.py draw theirs here too, with their own spacing and lanes)."""
    n_main, n_merge = lane_counts(num_cars)
    rng = np.random.RandomState(seed)  # numpy's legacy generator, draws in the documented order
    x_main = np.linspace(0.0, spacing * (n_main - 1), n_main) + rng.rand(n_main)
    offset = rng.rand()
    x_merge = spacing / 2 + 5.0 * (offset - 0.5) + np.linspace(0.0, spacing * (n_merge - 1), n_merge) + rng.rand(n_merge)
    v_main = 2.0 + rng.rand(n_main)
    v_merge = 2.0 + rng.rand(n_merge)
    x0 = np.zeros((num_cars, 4))
    x0[:n_main, 0], x0[:n_main, 1], x0[:n_main, 2] = x_main, main_lane_y, v_main
    x0[n_main:, 0], x0[n_main:, 1], x0[n_main:, 2] = x_merge, merge_lane_y, v_merge
    return x0


def merging_problem(num_cars: int, seed: int) -> GameProblem:
    x0 = initial_states(num_cars, seed)
    cost = QuadraticCost(x_ref=(0.0, Y_REF, V_REF, 0.0), Q_ref=Q_REF, R=R, Q=(0.0, 0.0, 0.0, 0.0))
    agents = [Agent(dynamics=KinematicBicycle(lf=LF, lr=LR), x0=x, cost=cost) for x in x0]
    return GameProblem(dt=DT, horizon=HORIZON, agents=agents,
                       collision=Collision(min_distance=MIN_DISTANCE, form="squared"))
