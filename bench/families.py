"""Seeded game families beyond the authors' merging benchmark (documented in docs/merging.md, "Other families").

A family is a small frozen spec plus a generator `problem(num_cars, seed)`; instances are drawn with numpy's legacy
`RandomState(seed)` in the order the generator's docstring gives, so an instance is reproducible from (family,
cars, seed) alone. `FAMILIES` maps the names `python -m app bench merge --family NAME` accepts to the specs."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bench import merging
from solver_cpp import Agent, Collision, GameProblem, KinematicBicycle, QuadraticCost


@dataclass(frozen=True)
class MergeFamily:
    """Two-lane merge as in bench/merging.py with other constants. Lengths in m, speeds in m/s, dt in s; Q_ref
    weights (x, y, v, theta) about x_ref = (-, y_ref, v_ref, 0); R weights (a, delta). Cars: floor(N/2) (at most
    N-1) in the main lane at y = main_lane_y, the rest at y = merge_lane_y. Draws: main-lane x = linspace(0,
    spacing (n_main - 1)) + U[0,1) each; one draw o; merging-lane x = spacing/2 + 5 (o - 0.5) + linspace(0, spacing
    (n_merge - 1)) + U[0,1) each; main-lane speeds 2 + U[0,1) each; merging-lane speeds 2 + U[0,1) each.
    steering_bound (rad): every car's |delta| <= steering_bound (inf: no control bounds, as in the authors' game)."""

    description: str
    dt: float = merging.DT
    horizon: int = merging.HORIZON
    lf: float = merging.LF
    lr: float = merging.LR
    main_lane_y: float = merging.MAIN_LANE_Y
    merge_lane_y: float = merging.MERGE_LANE_Y
    y_ref: float = merging.Y_REF
    v_ref: float = merging.V_REF
    Q_ref: tuple = merging.Q_REF
    R: tuple = merging.R
    min_distance: float = merging.MIN_DISTANCE
    form: str = "squared"
    spacing: float = merging.CAR_SPACING
    steering_bound: float = math.inf

    def problem(self, num_cars: int, seed: int) -> GameProblem:
        x0 = merging.initial_states(num_cars, seed, self.spacing, self.main_lane_y, self.merge_lane_y)
        cost = QuadraticCost(x_ref=(0.0, self.y_ref, self.v_ref, 0.0), Q_ref=self.Q_ref, R=self.R, Q=(0.0,) * 4)
        bounds = {} if math.isinf(self.steering_bound) else {
            "u_min": (-math.inf, -self.steering_bound), "u_max": (math.inf, self.steering_bound)}
        agents = [Agent(KinematicBicycle(lf=self.lf, lr=self.lr), x, cost, **bounds) for x in x0]
        return GameProblem(dt=self.dt, horizon=self.horizon, agents=agents,
                           collision=Collision(min_distance=self.min_distance, form=self.form))


@dataclass(frozen=True)
class StreamFamily:
    """Base of the two-stream games (crossing, head-on): cars 0, 2, 4, ... form one stream and 1, 3, ... the other,
    each stream queued at `spacing`; every car tracks its lane (lane_weight), heading (heading_weight) and v_ref
    (speed_weight). A subclass places car i in `_car`, which makes that car's random draws in its documented order."""

    description: str
    dt: float = 0.2
    horizon: int = 25
    lf: float = 1.0
    lr: float = 1.0
    v_ref: float = 2.0
    spacing: float = 4.5
    lane_weight: float = 0.5
    heading_weight: float = 1.0
    speed_weight: float = 0.05
    R: tuple = (0.3, 0.3)
    min_distance: float = 1.6
    form: str = "distance"

    def _car(self, i: int, queue: int, rng: np.random.RandomState) -> tuple[tuple, tuple, tuple]:
        """Initial state, x_ref and Q_ref of car i (the queue-th car of its stream)."""
        raise NotImplementedError

    def problem(self, num_cars: int, seed: int) -> GameProblem:
        if num_cars < 2:
            raise ValueError(f"cars must be at least 2, got {num_cars}")
        rng = np.random.RandomState(seed)
        agents = []
        for i in range(num_cars):
            x0, x_ref, Q_ref = self._car(i, i // 2, rng)
            agents.append(Agent(KinematicBicycle(lf=self.lf, lr=self.lr), x0,
                                QuadraticCost(x_ref=x_ref, R=self.R, Q_ref=Q_ref)))
        return GameProblem(dt=self.dt, horizon=self.horizon, agents=agents,
                           collision=Collision(min_distance=self.min_distance, form=self.form))


@dataclass(frozen=True)
class CrossingFamily(StreamFamily):
    """Two perpendicular one-lane streams through an intersection at the origin: cars 0, 2, 4, ... drive east along
    y = 0, cars 1, 3, ... north along x = 0, queued at `spacing` behind the first car of their stream, which starts
    `approach` before the origin. Each tracks its lane's centre line (weight lane_weight), heading (heading_weight)
    and v_ref. Draws: per car, in agent order, a position jitter U[0,1) (m, along its lane) and a speed v_ref - 0.5
    + U[0,1)."""

    approach: float = 5.0

    def _car(self, i, queue, rng):
        s = -self.approach - self.spacing * queue + rng.rand()
        v = self.v_ref - 0.5 + rng.rand()
        if i % 2 == 0:  # east-bound
            return ((s, 0.0, v, 0.0), (0.0, 0.0, self.v_ref, 0.0),
                    (0.0, self.lane_weight, self.speed_weight, self.heading_weight))
        return ((0.0, s, v, np.pi / 2), (0.0, 0.0, self.v_ref, np.pi / 2),  # north-bound
                (self.lane_weight, 0.0, self.speed_weight, self.heading_weight))


@dataclass(frozen=True)
class HeadOnFamily(StreamFamily):
    """A road along x whose centre line y = 0 every car tracks: cars 0, 2, 4, ... drive east from x = -gap/2,
    cars 1, 3, ... west (heading pi) from x = +gap/2, each stream queued at `spacing`; they must swerve to pass.
    Draws: per car, in agent order, a position jitter U[0,1) (m, along the road), a lateral offset
    lateral (2 U[0,1) - 1) (m) and a speed v_ref - 0.5 + U[0,1)."""

    horizon: int = 30
    spacing: float = 5.0
    lane_weight: float = 0.2
    gap: float = 20.0
    lateral: float = 0.3

    def _car(self, i, queue, rng):
        s = self.gap / 2 + self.spacing * queue + rng.rand()
        y = self.lateral * (2 * rng.rand() - 1)
        v = self.v_ref - 0.5 + rng.rand()
        east = i % 2 == 0
        theta = 0.0 if east else np.pi
        return ((-s if east else s, y, v, theta), (0.0, 0.0, self.v_ref, theta),
                (0.0, self.lane_weight, self.speed_weight, self.heading_weight))


FAMILIES = {
    "authors": MergeFamily("the authors' merging benchmark (bench/merging.py, docs/merging.md)"),
    "merge-dense": MergeFamily("cars packed closer (spacing 4.0 m), distance form, horizon 25, heading weight 2",
                               spacing=4.0, form="distance", horizon=25, Q_ref=(0.0, 0.1, 0.01, 2.0)),
    "merge-narrow": MergeFamily("narrow lanes at +-0.9 m, d_min 1.7 m, lf 0.8 / lr 1.2 m, dt 0.15 s, horizon 30, "
                                "heavier lane and speed weights, R (0.1, 0.5)",
                                main_lane_y=0.9, merge_lane_y=-0.9, y_ref=0.8, min_distance=1.7, lf=0.8, lr=1.2,
                                dt=0.15, horizon=30, spacing=4.6, Q_ref=(0.0, 0.3, 0.05, 2.0), R=(0.1, 0.5)),
    "merge-long": MergeFamily("long cars (lf = lr = 1.3 m), lanes at +-1.3 m, d_min 2.4 m distance form, dt 0.1 s, "
                              "horizon 40, v_ref 2.5 m/s, R (0.5, 0.2), steering bounded at +-0.6 rad as on a real car",
                              lf=1.3, lr=1.3, main_lane_y=1.3, merge_lane_y=-1.3, y_ref=1.2, min_distance=2.4,
                              form="distance", dt=0.1, horizon=40, v_ref=2.5, spacing=5.8, R=(0.5, 0.2),
                              steering_bound=0.6),
    "crossing": CrossingFamily("two perpendicular streams through an intersection, d_min 1.6 m distance form"),
    "head-on": HeadOnFamily("opposite streams on one road, swerving to pass, d_min 1.6 m distance form"),
}


def family_problem(name: str, num_cars: int, seed: int) -> GameProblem:
    if name not in FAMILIES:
        raise ValueError(f"unknown family {name!r}; choose from {', '.join(FAMILIES)}")
    return FAMILIES[name].problem(num_cars, seed)
