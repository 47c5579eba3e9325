"""Seeded game families beyond the authors' merging benchmark (documented in docs/merging.md, "Other families").

A family is a small frozen spec plus a generator `problem(num_cars, seed)`; instances are drawn with numpy's legacy
`RandomState(seed)` in the order the generator's docstring gives, so an instance is reproducible from (family,
cars, seed) alone. `FAMILIES` maps the names `python -m app bench merge --family NAME` accepts to the specs:
`TUNED_FAMILIES`, the six the solver's defaults were tuned on, and `HELD_OUT_FAMILIES`, fixed before any solve of
them and measured only on seeds 50-99."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from bench import merging
from solver_cpp import Agent, Collision, GameProblem, KinematicBicycle, KinematicBicycleFrenet, QuadraticCost


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
        agents = [Agent(KinematicBicycle(lf=self.lf, lr=self.lr), x, cost) for x in x0]
        problem = GameProblem(dt=self.dt, horizon=self.horizon, agents=agents,
                              collision=Collision(min_distance=self.min_distance, form=self.form))
        return problem if math.isinf(self.steering_bound) else bound_steering(problem, self.steering_bound)


@dataclass(frozen=True)
class StreamFamily:
    """Base of the two-stream games (crossing, head-on): cars 0, 2, 4, ... form one stream and 1, 3, ... the other,
    each stream queued at `spacing`; every car tracks its lane (lane_weight), heading (heading_weight) and v_ref
    (speed_weight). A subclass places car i in `_car`, which makes that car's random draws in its documented order;
    car i is the (i // streams)-th of its stream."""

    streams: ClassVar[int] = 2

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

    def _model(self):
        return KinematicBicycle(lf=self.lf, lr=self.lr)

    def problem(self, num_cars: int, seed: int) -> GameProblem:
        if num_cars < 2:
            raise ValueError(f"cars must be at least 2, got {num_cars}")
        rng = np.random.RandomState(seed)
        agents = []
        model = self._model()
        for i in range(num_cars):
            x0, x_ref, Q_ref = self._car(i, i // self.streams, rng)
            agents.append(Agent(model, x0, QuadraticCost(x_ref=x_ref, R=self.R, Q_ref=Q_ref)))
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


@dataclass(frozen=True)
class FourWayFamily(StreamFamily):
    """A four-way intersection of two two-lane roads (along the x and y axes) crossing at the origin, right-hand
    traffic, every car going straight: car i drives east (i % 4 = 0) along y = -lane, north (1) along x = +lane, west
    (2) along y = +lane or south (3) along x = -lane, as the (i // 4)-th car of its queue. The first car of a queue
    starts `approach` (m, along its lane) before the crossing road's axis, the others `spacing` apart behind it. The
    lanes cross at (+-lane, +-lane): east-bound and north-bound at (lane, -lane), east and south at (-lane, -lane),
    west and north at (lane, lane), west and south at (-lane, lane); opposite lanes pass 2 lane apart. Each car tracks
    its lane (lane_weight), heading (heading_weight) and v_ref (speed_weight). Draws: per car, in agent order, a
    position jitter U[0,1) (m, away from the intersection) and a speed v_ref - 0.5 + U[0,1)."""

    streams: ClassVar[int] = 4
    lane: float = 1.1
    approach: float = 7.0

    def _car(self, i, queue, rng):
        d = self.approach + self.spacing * queue + rng.rand()
        v = self.v_ref - 0.5 + rng.rand()
        w, along, across = self.lane, (0.0, 0.0, self.speed_weight, self.heading_weight), self.lane_weight
        direction = i % 4
        if direction == 0:  # east-bound
            return (-d, -w, v, 0.0), (0.0, -w, self.v_ref, 0.0), (0.0, across, *along[2:])
        if direction == 1:  # north-bound
            return (w, -d, v, np.pi / 2), (w, 0.0, self.v_ref, np.pi / 2), (across, 0.0, *along[2:])
        if direction == 2:  # west-bound
            return (d, w, v, np.pi), (0.0, w, self.v_ref, np.pi), (0.0, across, *along[2:])
        return (-w, d, v, -np.pi / 2), (-w, 0.0, self.v_ref, -np.pi / 2), (across, 0.0, *along[2:])  # south-bound


@dataclass(frozen=True)
class RingFamily(StreamFamily):
    """The circulating lanes of a two-lane roundabout: a ring road whose centre line is a circle of `radius` about
    the origin, driven counter-clockwise, in the track coordinates of KinematicBicycleFrenet (state [s, ey, v, epsi]:
    s along the centre line from the point (radius, 0), ey to the left, i.e. towards the centre; the curvature table
    holds 1/radius at `samples` points around the closed ring). Inner lane at ey = +lane, outer lane at ey = -lane.
    Cars 0, 2, 4, ... start in the inner lane and take the outer one (towards the exits), cars 1, 3, ... start in the
    outer lane (just entered) and take the inner one: the two streams weave. Car i is the (i // 2)-th of its lane,
    `spacing` apart along s, the outer lane's queue starting spacing / 2 ahead of the inner one's. In the plane car i
    is at (radius - ey) (cos(s / radius), sin(s / radius)). Collision distances are measured in track coordinates
    (s, ey). Draws: per car, in agent order, a jitter U[0,1) (m, along s) and a speed v_ref - 0.4 + 0.8 U[0,1)."""

    radius: float = 9.0
    lane: float = 1.05
    samples: int = 90

    def _car(self, i, queue, rng):
        inner = i % 2 == 0
        s = self.spacing * queue + (0.0 if inner else self.spacing / 2) + rng.rand()
        v = self.v_ref - 0.4 + 0.8 * rng.rand()
        start, target = (self.lane, -self.lane) if inner else (-self.lane, self.lane)
        return ((s, start, v, 0.0), (0.0, target, self.v_ref, 0.0),
                (0.0, self.lane_weight, self.speed_weight, self.heading_weight))

    def _model(self):
        return KinematicBicycleFrenet(lf=self.lf, lr=self.lr, kappa=np.full(self.samples, 1.0 / self.radius),
                                      ds=2 * np.pi * self.radius / self.samples, closed=True)


# The six families the solver's defaults were measured and tuned on (seeds 0-7; docs/benchmarks.md, "Tuned and held
# out").
TUNED_FAMILIES = {
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

# Families added after the tuning, their constants fixed before any solve of them (issue #31): measured on seeds
# 50-99 only, and never used to choose a setting.
HELD_OUT_FAMILIES = {
    "merge-close": MergeFamily("cars 4.2 m apart against d_min 2.2 m distance form, lanes at +-1.2 m (y_ref 1.1), "
                               "lf 1.1 / lr 0.9, dt 0.15 s, horizon 24, v_ref 2.2, Q_ref (0, 0.15, 0.02, 1.5), "
                               "R (0.2, 0.4)",
                               spacing=4.2, min_distance=2.2, form="distance", lf=1.1, lr=0.9, dt=0.15, horizon=24,
                               main_lane_y=1.2, merge_lane_y=-1.2, y_ref=1.1, v_ref=2.2, Q_ref=(0.0, 0.15, 0.02, 1.5),
                               R=(0.2, 0.4)),
    "merge-quick": MergeFamily("coarse steps: dt 0.25 s, horizon 20, lanes at +-1.15 m (y_ref 1.05), d_min 2.1 m "
                               "squared form, lf 0.95 / lr 1.05, spacing 5.0, v_ref 1.8, Q_ref (0, 0.05, 0.02, 0.6), "
                               "R (0.4, 0.2), steering bounded at +-0.7 rad",
                               dt=0.25, horizon=20, main_lane_y=1.15, merge_lane_y=-1.15, y_ref=1.05, min_distance=2.1,
                               form="squared", lf=0.95, lr=1.05, spacing=5.0, v_ref=1.8, Q_ref=(0.0, 0.05, 0.02, 0.6),
                               R=(0.4, 0.2), steering_bound=0.7),
    "four-way": FourWayFamily("a four-way intersection, right-hand traffic, four straight-through queues on lanes "
                              "1.1 m off the road axes, first cars 7 m before the crossing road, queues 5.2 m; d_min "
                              "1.8 m squared form; lf 0.9 / lr 1.2, dt 0.2 s, horizon 32; lane weight 0.8, heading "
                              "1.5, speed 0.08, R (0.25, 0.6)",
                              dt=0.2, horizon=32, lf=0.9, lr=1.2, v_ref=2.0, spacing=5.2, lane_weight=0.8,
                              heading_weight=1.5, speed_weight=0.08, R=(0.25, 0.6), min_distance=1.8, form="squared",
                              lane=1.1, approach=7.0),
    "ring": RingFamily("the circulating lanes of a roundabout: a ring of radius 9 m, lanes at ey +-1.05 m, inner and "
                       "outer streams swapping lanes (track coordinates); queues 4.4 m; d_min 1.8 m distance form; "
                       "lf 1.2 / lr 0.8, dt 0.12 s, horizon 36, v_ref 2.4; lane weight 0.6, heading 0.8, speed 0.04, "
                       "R (0.15, 0.8)",
                       dt=0.12, horizon=36, lf=1.2, lr=0.8, v_ref=2.4, spacing=4.4, lane_weight=0.6,
                       heading_weight=0.8, speed_weight=0.04, R=(0.15, 0.8), min_distance=1.8, form="distance",
                       radius=9.0, lane=1.05, samples=90),
}

FAMILIES = {**TUNED_FAMILIES, **HELD_OUT_FAMILIES}
# Names `--family` accepts besides the families' own.
FAMILY_GROUPS = {"all": tuple(FAMILIES), "tuned": tuple(TUNED_FAMILIES), "held-out": tuple(HELD_OUT_FAMILIES)}


def family_names(text: str) -> list[str]:
    """The families a comma-separated list of family and group names selects, in order, each once."""
    names: list[str] = []
    for part in filter(None, (p.strip() for p in text.split(","))):
        if part not in FAMILIES and part not in FAMILY_GROUPS:
            raise ValueError(f"unknown family {part!r}; choose from {', '.join(FAMILIES)} or a group "
                             f"({', '.join(FAMILY_GROUPS)})")
        names += [n for n in FAMILY_GROUPS.get(part, (part,)) if n not in names]
    if not names:
        raise ValueError("no family named")
    return names


def family_problem(name: str, num_cars: int, seed: int, steering_bound: float = math.inf) -> GameProblem:
    """Instance `seed` of family `name` with `num_cars` cars; steering_bound (rad, > 0): every car's |delta| bounded
    at it as well (the tighter of it and the family's own bound), a variant of the family, not one of them."""
    if name not in FAMILIES:
        raise ValueError(f"unknown family {name!r}; choose from {', '.join(FAMILIES)}")
    problem = FAMILIES[name].problem(num_cars, seed)
    return problem if math.isinf(steering_bound) else bound_steering(problem, steering_bound)


def bound_steering(problem: GameProblem, bound: float) -> GameProblem:
    """problem with every car's steering (control 1 of the bicycles, u = (a, delta)) bounded at |delta| <= bound
    (rad), keeping a tighter bound the car has."""
    if not bound > 0:
        raise ValueError(f"steering bound must be > 0 rad, got {bound}")
    agents = []
    for i, a in enumerate(problem.agents):
        if not isinstance(a.dynamics, (KinematicBicycle, KinematicBicycleFrenet)):
            raise ValueError(f"agent {i}: a steering bound needs a bicycle model, got {type(a.dynamics).__name__}")
        lo = list(a.u_min) if a.u_min is not None else [-math.inf, -math.inf]
        hi = list(a.u_max) if a.u_max is not None else [math.inf, math.inf]
        lo[1], hi[1] = max(lo[1], -bound), min(hi[1], bound)
        agents.append(dataclasses.replace(a, u_min=tuple(lo), u_max=tuple(hi)))
    return dataclasses.replace(problem, agents=agents)
