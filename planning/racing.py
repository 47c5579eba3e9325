"""Receding-horizon racing planners on the track (Frenet kinematic bicycle, state [s, ey, v, epsi],
control [a, delta]); both solved with the project's C++ solver (solver_cpp).

RacingPlanner (RD3G): a game of our car (agent 0) and the other cars it plans with (agents 1..M, the
race layer picks them: race.planning.interacting_cars), all with the racing cost (lead term
lead_weight * (s_j - s_i) per step and opponent plus tracking terms), a shared collision constraint on
(s, ey) between every pair, track limits as bounds on ey, the car's acceleration/steering limits as
control bounds.

MPCOpponent: one agent with the same cost; every other car is predicted at constant speed along the
track at its current lateral offset and avoided as a moving obstacle. It does not model that the
other cars react to it.

Both race the centre line (PlannerConfig.line "centre": the constant lateral reference raceline_ey_m,
the cornering cap on the speed bound) or the track's racing line ("racing": its offset and speed at
each horizon stage as the cost's stage-varying reference, planning.reference, the speed bound also
within the tyre limit on the path of the car's last plan, path_speed_cap).

Both take the other cars as rows of an (M, 4) array (one (4,) state is one car); their s must be in
the planning car's frame (the race layer unwraps laps: race.planning.RacePlanners). With a single agent the solver's lead term has no opponent, so the progress reward
-lead_weight * s is written as the quadratic lead_weight/(2D) (s - (s0 + D))^2 with D far ahead
(its gradient is -lead_weight (1 - (s - s0)/D), within 2 % over the plan for D = 100 m); the
opponent's progress is a constant for this planner.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from solver_cpp import Agent, Collision, GameProblem, GameResult, Obstacle, PairDistance, QuadraticCost, Solver, WarmStart

from .commands import CommandMapper
from .config import PlannerConfig, solver_settings
from .frenet import EPSI, EY, S, V, FrenetTrackModel, frenet_separation, min_turn_radius, path_curvature
from .reference import path_speed_bounds, planner_racing_line, stage_reference

_PROGRESS_ANCHOR_M = 100.0  # D above
# Smallest collision distance a relaxed problem gets (m). The solver rejects d_min <= 0, which the
# relaxation below produced when the cars were within 1 cm (they pass through each other in the
# simulator after a contact); below the floor the k = 1 constraint may be infeasible, and then the
# usual fallback applies.
_MIN_COLLISION_DISTANCE_M = 0.01
# Largest speed drop (m/s) below the current speed that one plan's speed bound asks for
# (follow_speed_cap, corner_speed_cap): reachable with 2 m/s^2 over the first planning step.
_BOUND_DROP_MPS = 0.2


@dataclass
class Plan:
    """One planning step. x: (N, T+1, 4) planned (or predicted) trajectories, agent 0 = the planning
    car; u: (T, 2) the planning car's controls; `used` says whether the solve was used ("converged",
    "accepted": not converged but feasible within accept_violation_m) or not ("fallback": the car
    tracks the last plan it used in closed loop for this step, see tracking_control). `error`: the
    exception that stopped planning this step (see fallback_plan), else None."""

    x: np.ndarray
    u: np.ndarray
    status: str
    iterations: int
    solve_time_s: float
    max_violation: float
    used: str
    d_min: float
    ey_bound: float
    error: str | None = None

    @property
    def control(self) -> np.ndarray:
        return self.u[0]


class _RecedingHorizon:
    n_agents = 1

    def __init__(self, track_model: FrenetTrackModel, mapper: CommandMapper, config: PlannerConfig,
                 control_period_s: float) -> None:
        self.tm = track_model
        self.mapper = mapper
        self.config = config
        self.control_period_s = float(control_period_s)
        self._prev: GameResult | None = None
        # The own car's states (T+1, 4) along the last plan it used, advanced one control period per
        # fallback step since, and the time (s) it has been advanced: what a fallback tracks
        # (_track_previous) while the plan still covers the present.
        self._reference: np.ndarray | None = None
        self._reference_age_s = 0.0
        # Set up at the first plan, then updated every plan (same structure all race long).
        self._solver: Solver | None = None
        self._solvers: dict[int, Solver] = {}       # one per number of agents (the game's player set changes)
        self._prev_ids: tuple = ()                  # the cars (ids) of _prev's agents 1.., to map its warm start
        self._warm_settings = solver_settings(config.solver)
        self._game_settings: dict[int, object] = {}  # warm settings of games of more than two players
        self._cold_settings = solver_settings(config.solver, config.cold_start_solver)
        # The retry after a failed warm start (from _tracking_guess): the warm settings at the default barrier weight.
        self._retry_settings = solver_settings(config.solver, {"barrier": {"rho_init": None}})
        self._shift_weights: dict[int, tuple] = {}  # _shifted's interpolation per series length
        # config.line "racing": the line this car follows (its own limits and top speed; cached per track).
        self.line = (planner_racing_line(track_model.track, track_model.car, config.top_speed_mps, config)
                     if config.line == "racing" else None)
        self._lines = {} if self.line is None else {float(config.top_speed_mps): self.line}  # line_for, per top speed

    def reset(self) -> None:
        self._prev = None
        self._reference = None
        self._reference_age_s = 0.0
        self.mapper.reset()

    @property
    def preferred_speed(self) -> float:
        """This car's speed reference (m/s): reference_speed_mps, or the top speed."""
        c = self.config
        return c.top_speed_mps if c.reference_speed_mps is None else c.reference_speed_mps

    def _cost(self, top_speed: float, reference: float | None = None, x0=None, stages=None) -> QuadraticCost:
        """The racing cost at speed reference min(reference, top_speed) (reference None: top_speed).
        Following the racing line (self.line) from state x0: the stage-varying reference (x_ref_steps)
        of the line's offset and speed at each stage (``stages``: _stages(x0) if already computed), the
        speed at most that constant reference."""
        c = self.config
        v_ref = top_speed if reference is None else min(float(reference), top_speed)
        cost = QuadraticCost(x_ref=[0.0, c.raceline_ey_m, v_ref, 0.0], Q_ref=[0.0, c.q_lateral, c.q_speed, c.q_heading],
                             R=[c.r_accel, c.r_steer])
        if self.line is not None and x0 is not None:
            stages = self._stages(x0) if stages is None else stages
            steps = np.tile(np.asarray(cost.x_ref, dtype=float), (c.horizon, 1))
            steps[:, EY], steps[:, V] = stages.ey, np.minimum(stages.v, v_ref)
            cost.x_ref, cost.x_ref_steps = list(steps[-1]), steps
        return cost

    def line_for(self, top_speed: float):
        """The racing line of a car of this model with top speed ``top_speed`` (m/s): this car's own line at
        its top speed; None on the centre line. Why: the line's speed profile is capped at the car's top
        speed, so another car of the game raced on ours (a faster opponent on the 1.6 m/s line of a slow
        RD3G car) got a speed bound below its speed in every plan, a bound the real car never kept: the
        shifted warm start broke it at k = 1 and the solve fell back (docs/racing.md)."""
        if self.line is None:
            return None
        top = float(top_speed)
        if top not in self._lines:
            self._lines[top] = planner_racing_line(self.tm.track, self.tm.car, top, self.config)
        return self._lines[top]

    def _stages(self, x0, line=None):
        """The racing line's references at this plan's stages from state x0 (planning.reference) along
        ``line`` (default: this car's, self.line); None on the centre line."""
        line = self.line if line is None else line
        if line is None:
            return None
        c, limits = self.config, line.limits
        return stage_reference(line, self.tm.track.curvature, float(x0[S]), float(x0[V]), c.horizon,
                               c.plan_dt_s, limits.accel_mps2, limits.brake_mps2)

    def speed_cap(self, x, top_speed: float, stages=None) -> float:
        """Speed bound (m/s) of a plan from state x: corner_speed_cap on the centre line; following
        the racing line, the line's speed at the first stage (``stages``: _stages(x) if already computed;
        its profile already brakes for the turns ahead), asking for at most 0.2 m/s below the current speed
        per plan."""
        if self.line is None:
            return self.corner_speed_cap(x, top_speed)
        v_line = float((self._stages(x) if stages is None else stages).v[0])
        return float(min(top_speed, max(v_line, float(x[V]) - _BOUND_DROP_MPS)))

    def path_speed_cap(self, x, top_speed: float) -> float:
        """Speed bound (m/s) of this car's plan from state x following the racing line: the tyre limit along
        the path of its last plan (shifted to now; planning.reference.path_speed_bounds at
        path_lateral_accel_mps2 and max_brake_mps2, the path's curvature from the plan's steering) at the
        first planned stage, asking for at most 0.2 m/s below the current speed per plan; top_speed on the
        centre line or before the first plan. Why: the line's speed profile holds on the line's path, and
        the kinematic planning model has no tyre limit, so a car off the line (e.g. 0.16 m outside it
        entering a 0.3 m turn) planned the line's speed on a tighter path and slid off the track."""
        if self.line is None or self._prev is None:
            return float(top_speed)
        c, g = self.config, self.tm.car.geometry
        x_prev, u_prev = self._shifted(np.asarray(self._prev.x)[:1])[0], self._shifted(np.asarray(self._prev.u)[:1])[0]
        bounds = path_speed_bounds(x_prev[:-1, V], path_curvature(u_prev[:, 1], g.lf_m, g.lr_m), c.plan_dt_s,
                                   c.path_lateral_accel_mps2, c.max_brake_mps2)
        v_path = float(np.min(bounds[:2]))  # stage 1 ends segment 0 and starts segment 1
        return float(min(top_speed, max(v_path, float(x[V]) - _BOUND_DROP_MPS)))

    @staticmethod
    def _set_reference(cost: QuadraticCost, index: int, value: float, weight: float | None = None) -> None:
        """Sets component ``index`` of the cost's reference (every stage's) to ``value``, its weight to ``weight``."""
        cost.x_ref = [*cost.x_ref[:index], float(value), *cost.x_ref[index + 1:]]
        if cost.x_ref_steps is not None:
            cost.x_ref_steps[:, index] = value
        if weight is not None:
            cost.Q_ref = [*cost.Q_ref[:index], float(weight), *cost.Q_ref[index + 1:]]

    def ey_limits(self, s_values) -> tuple[float, float]:
        """(lowest, highest) ey of a plan over the window of the given progress values: the track-limit
        bound, within which the inside of every turn keeps the radius the car turns at the planner's
        steering limit (FrenetTrackModel.ey_limits; left turns at delta_max, right turns at delta_min).
        That limit holds a path at a constant offset round the turn; a racing line cuts across the turn
        on a wider radius (tightest 0.228 m on the tile tracks) and touches the inside at its apex, so
        following one the limits also keep the line's own offsets over the window plus line_margin_m
        (within the track-limit bound)."""
        g = self.tm.car.geometry
        low, high = self.tm.ey_limits(s_values, min_turn_radius(g.lf_m, g.lr_m, self.mapper.delta_max),
                                      min_turn_radius(g.lf_m, g.lr_m, self.mapper.delta_min))
        if self.line is None:
            return low, high
        bound = self.tm.ey_bound(s_values)
        line_ey = self.line.lateral_offset(np.mod(self.tm.window(s_values), self.tm.track.length))
        margin = self.config.line_margin_m
        return (max(min(low, float(np.min(line_ey)) - margin), -bound),
                min(max(high, float(np.max(line_ey)) + margin), bound))

    def _agent(self, x0, top_speed: float, ey_limits: tuple[float, float], cost: QuadraticCost, lead: float) -> Agent:
        a_min, a_max = self.mapper.acceleration_bounds(float(x0[V]))
        return Agent(self.tm.model, x0=list(map(float, x0)), cost=cost,
                     u_min=[a_min, self.mapper.delta_min], u_max=[a_max, self.mapper.delta_max],
                     # Racing plans never reverse (a car rolling backwards may keep its speed, not grow it);
                     # 1 mm/s below a top speed of 0 (a car held behind a standing one) keeps the bounds apart.
                     x_min=[-np.inf, ey_limits[0], min(0.0, float(x0[V]), top_speed - 1e-3), -np.inf],
                     x_max=[np.inf, ey_limits[1], top_speed, np.inf],
                     lead_weight=lead, lead_index=S)

    def _shifted(self, a: np.ndarray) -> np.ndarray:
        """Per-agent time series (N, n, ...) advanced by one control period (interpolated: the
        planning step is longer), the last sample held."""
        n = a.shape[1]
        if n not in self._shift_weights:  # the same few lengths every step (T, T+1)
            t = np.minimum(np.arange(n) + self.control_period_s / self.config.plan_dt_s, n - 1)
            i0 = np.floor(t).astype(int)
            self._shift_weights[n] = (i0, np.minimum(i0 + 1, n - 1), t - i0)
        i0, i1, w = self._shift_weights[n]
        w = w.reshape((1, n) + (1,) * (a.ndim - 2))
        return (1 - w) * a[:, i0] + w * a[:, i1]

    def _warm_start(self, ids: tuple = ()) -> WarmStart | None:
        """Previous plan shifted by one control period. ``ids``: the cars of this plan's agents 1.. ;
        when they differ from the previous plan's, each car keeps its own rows (own controls and
        dynamics multipliers) and a car new to the game starts from zero controls."""
        if self._prev is None:
            return None
        u, lam = self._shifted(self._prev.u), self._shifted(self._prev.lam)
        if ids == self._prev_ids:
            return WarmStart(u=u, lam=lam)
        rows = {car: k + 1 for k, car in enumerate(self._prev_ids)}
        pick = [0] + [rows.get(car, -1) for car in ids]
        u_new = np.zeros((len(pick),) + u.shape[1:])
        lam_new = np.zeros((len(pick),) + lam.shape[1:])
        for k, r in enumerate(pick):
            if r >= 0:
                u_new[k], lam_new[k] = u[r], lam[r]
        return WarmStart(u=u_new, lam=lam_new)

    def _stage_refs(self, agent: Agent) -> np.ndarray:
        """(T, n) the agent's cost reference at each stage (its per-step references, or the one held)."""
        if agent.cost.x_ref_steps is None:
            return np.tile(agent.cost.x_ref, (self.config.horizon, 1))
        return np.asarray(agent.cost.x_ref_steps, dtype=float)

    def _inside_bounds(self, problem: GameProblem, warm: WarmStart | None) -> WarmStart | None:
        """Following the racing line: the warm start with each agent's steering, from two steps before the
        first planned state that leaves its track-limit bounds (the heading acts on ey from two steps on),
        replaced by closed-loop tracking (tracking_control) of the agent's cost's lateral reference at each
        stage, held inside the bounds; accelerations kept. Why: a plan often ends on a bound (nothing beyond
        the horizon pulls it back), and shifted by one control period its held last control carries the
        last stage over the bound. Following the racing line, 3 cm inside the bound, most warm starts were
        infeasible so, and an infeasible warm start is where the solves fell back (oval, `batch --line
        racing --races 1 --seed 3`: 69 of 71 fallbacks; 16 % of such starts fell back, 1 % of feasible ones;
        docs/racing.md). Lowering the accelerations of warm starts above the speed bound as well made the
        solo laps slower (buzzracer:full 10.74 s against 9.71 s) with more fallbacks (37 against 19). On the centre line
        the plans stay clear of the bounds (1.7 % fallbacks), and its measured races stay as they are."""
        if warm is None or self.line is None:
            return warm
        c = self.config
        model = self.tm.rollout_model(c.plan_dt_s)
        u = np.array(warm.u, dtype=float)
        for i, agent in enumerate(problem.agents):
            lo, hi = float(agent.x_min[EY]), float(agent.x_max[EY])
            x = np.asarray(model.rollout(np.asarray(agent.x0, dtype=float), u[i]))
            out = np.flatnonzero((x[1:, EY] > hi) | (x[1:, EY] < lo))
            if len(out) == 0:
                continue
            refs = self._stage_refs(agent)
            for j in range(max(int(out[0]) - 1, 0), c.horizon):
                x_ref = np.array([x[j, S], float(np.clip(refs[j, EY], lo, hi)), x[j, V], 0.0])
                u[i, j, 1] = np.clip(self.tracking_control(x[j], x_ref, 0.0, max(-lo, hi))[1],
                                     agent.u_min[1], agent.u_max[1])
                x[j + 1] = np.asarray(model.rollout(x[j], u[i, j][None]))[-1]
        return WarmStart(u=u, lam=warm.lam, mu=warm.mu)

    def _tracking_guess(self, problem: GameProblem, warm: WarmStart) -> WarmStart:
        """The retry's initial guess, on either line: every agent's controls by closed-loop tracking
        (tracking_control) of its cost's stage references (lateral offset inside its track-limit bounds,
        speed at most its top speed), the multipliers of the warm start. Why not the solver's own guess, zero
        controls: straight wheels in a turn run to its outside, and the retry's plan with them. On the oval's
        centre line (`race --track oval --line centre --laps 2`, solo against a slow car) a retry in the 1 m
        turn from ey 0.0-0.18 m planned onto the outer bound; the car followed, the kinematic plan's sideslip
        under-stated its drift there, it crossed the bound, every solve from beyond it failed, and the
        fallbacks held it outside until it left the track (RD3G in 3 and MPC in 6 of 8 runs with its speed
        perturbed by 1-30 um/s; none with this guess; docs/racing.md)."""
        c = self.config
        model = self.tm.rollout_model(c.plan_dt_s)
        u = np.zeros_like(np.asarray(warm.u, dtype=float))
        for i, agent in enumerate(problem.agents):
            lo, hi, top = float(agent.x_min[EY]), float(agent.x_max[EY]), float(agent.x_max[V])
            refs = self._stage_refs(agent)
            x = np.asarray(agent.x0, dtype=float)
            for j in range(c.horizon):
                x_ref = np.array([x[S], float(np.clip(refs[j, EY], lo, hi)), min(float(refs[j, V]), top), 0.0])
                u[i, j] = np.clip(self.tracking_control(x, x_ref, 0.0, max(-lo, hi), top), agent.u_min, agent.u_max)
                x = np.asarray(model.rollout(x, u[i, j][None]))[-1]
        return WarmStart(u=u, lam=warm.lam, mu=warm.mu)

    def tracking_control(self, x0, x_ref, a_ref: float, ey_bound: float, top_speed: float | None = None) -> np.ndarray:
        """Closed-loop fallback control [a, delta] when no usable plan exists: the Stanley lateral
        law on the Frenet errors to the reference state x_ref (the last used plan's state for now,
        its ey clipped to the track-limit bound) plus curvature feed-forward, and a proportional
        speed loop around the reference acceleration, never past top_speed (default: the car's top
        speed); clipped to the control bounds. Replaying the previous plan open loop instead let
        small errors grow until the car left the track."""
        c = self.config
        x0 = np.asarray(x0, dtype=float)
        g = self.tm.car.geometry
        kappa = float(self.tm.track.curvature(np.mod(x0[S], self.tm.track.length)))
        ey_target = float(np.clip(x_ref[EY], -ey_bound, ey_bound))
        v = max(float(x0[V]), 0.3)
        delta = (math.atan((g.lf_m + g.lr_m) * kappa) - (x0[EPSI] - float(x_ref[EPSI]))
                 - math.atan(c.fallback_lateral_gain * (x0[EY] - ey_target) / v))
        a_min, a_max = self.mapper.acceleration_bounds(float(x0[V]))
        a = a_ref + c.fallback_speed_gain * (float(x_ref[V]) - x0[V])
        top = c.top_speed_mps if top_speed is None else float(top_speed)
        a = min(a, (top - x0[V]) / c.plan_dt_s)  # never plan past the top speed
        return np.array([np.clip(a, a_min, a_max), np.clip(delta, self.mapper.delta_min, self.mapper.delta_max)])

    def _feasible_limits(self, x0s, ey_limits: tuple[float, float], d_min: float, along_track_scale: float,
                         obstacle_positions=()) -> tuple[tuple[float, float], float, np.ndarray]:
        """Track-limit bounds (lowest, highest ey) and collision distance relaxed just enough that the
        problem is feasible from the current states. A car beyond a bound (or heading out of it) cannot be
        back inside at k = 1 (the first planned position hardly depends on the controls), nor can two cars
        closer than d_min be d_min apart; the solver then fails at once (line search) and the car used to
        be driven open loop until it left the track. Bound: the farthest ey of a full-lock recovery towards
        the middle of the bounds over the horizon, if that is beyond the nominal bound on its side (the
        lateral cost then pulls the car back); distance: at most the current separation and the one at k = 1
        with zero controls (both measured as the constraint does, frenet_separation with along_track_scale),
        minus 1 cm (the bound gets 3 cm of room: with 1-2 cm the solves from such states stalled), but never
        below _MIN_COLLISION_DISTANCE_M. Returns (bounds, the smallest pair's distance, each pair's
        distance: a symmetric matrix over x0s then obstacle_positions; only the pairs that start too close
        are relaxed, the others keep d_min)."""
        c = self.config
        model = self.tm.rollout_model(c.plan_dt_s)
        low, high = ey_limits
        middle = 0.5 * (low + high)
        first = []
        for x0 in x0s:
            x0 = np.asarray(x0, dtype=float)
            side = 1.0 if x0[EY] >= middle else -1.0  # the bound the car is nearer
            u = np.zeros((c.horizon, 2))
            u[:, 1] = self.mapper.delta_min if side > 0 else self.mapper.delta_max
            x = np.asarray(model.rollout(x0, u))
            # recovery: steer towards the middle until heading inward, then the bound is not needed further
            inward = -side * x[:, EPSI] > 0
            stop = int(np.argmax(inward)) if inward.any() else c.horizon
            reach = side * x[1: stop + 2, EY]  # x0 itself is not constrained
            if side > 0 and float(np.max(reach)) > high:
                high = float(np.max(reach)) + 0.03  # interior room for the barrier
            elif side < 0 and -float(np.max(reach)) < low:
                low = -float(np.max(reach)) - 0.03
            first.append(np.asarray(model.rollout(x0, np.zeros((1, 2))))[:, :2])
        # A relaxed track-limit bound is relaxed on both sides (the oval's cold solves from a car beyond the
        # bound were usable and turned back more often so); a side held at a turn's inner limit keeps it.
        outer, relaxed = max(-ey_limits[0], ey_limits[1]), max(-low, high)
        if relaxed > outer:
            low, high = (-relaxed if ey_limits[0] == -outer else low), (relaxed if ey_limits[1] == outer else high)
        positions = first + [np.asarray(o)[:2] for o in obstacle_positions]
        nominal = float(d_min)
        pair = np.full((len(positions), len(positions)), nominal)
        for i in range(len(first)):  # obstacles constrain the agents only, not each other
            for j in range(i + 1, len(positions)):
                gap = positions[i] - positions[j]
                within_gap = float(np.min(frenet_separation(gap[:, 0], gap[:, 1], along_track_scale))) - 0.01
                pair[i, j] = pair[j, i] = max(min(nominal, within_gap), _MIN_COLLISION_DISTANCE_M)
                d_min = min(d_min, within_gap)
        return (low, high), max(d_min, _MIN_COLLISION_DISTANCE_M), pair

    def corner_speed_cap(self, x, top_speed: float) -> float:
        """Speed bound (m/s) for a plan from state x: top_speed, lowered to sqrt(max_lateral_accel /
        |kappa|) for the largest centre-line curvature between the car and the end of its reach
        (top_speed x horizon + 0.5 m), but asking for at most 0.2 m/s below the current speed per plan
        (reachable: 2 m/s^2 over the first planning step). The kinematic planning model has no tyre
        limit, so without this the planners drove into the twisty track's 0.4 m turns at 2 m/s (1 g)
        and the simulated cars slid off. On the oval's 1 m turns the cap is 2.05 m/s, above both top
        speeds of the batch: no change there."""
        c = self.config
        reach = top_speed * c.horizon * c.plan_dt_s + 0.5
        s = np.mod(float(x[S]) + np.arange(0.0, reach, 0.02), self.tm.track.length)
        kappa = float(np.max(np.abs(self.tm.track.curvature(s))))
        if kappa <= 0:
            return float(top_speed)
        v_corner = math.sqrt(c.max_lateral_accel_mps2 / kappa)
        return float(min(top_speed, max(v_corner, float(x[V]) - _BOUND_DROP_MPS)))

    def _track_previous(self, x0, ey_bound: float, top_speed: float | None = None, u_all=None,
                        others=()) -> np.ndarray:
        """Controls (N, T, 2) of the previous plan shifted by one control period (``u_all``: those
        controls already mapped to this plan's agents, _warm_start), the planning car's first control
        replaced by the closed-loop tracking control towards _fallback_reference. Not towards the
        previous plan: after a fallback that is the car's own rollout, so a run of fallbacks saw no
        error and held the car's heading, off the track. ``others``: the other cars' (s, ey) now, which a
        fallback does not steer towards (_clear_of_alongside); where that holds the target off a car alongside,
        the reference heading is the track's, not the plan's: the plan's heading across kept turning the car
        into the car beside it (4-car races on `full` with the racing line, seeds 13 and 16)."""
        u_all = self._shifted(self._prev.u) if u_all is None else np.array(u_all)
        x_ref, a_ref = self._fallback_reference(x0, top_speed)
        x_ref = np.array(x_ref, dtype=float)
        ey_clear = self._clear_of_alongside(x0, float(x_ref[EY]), others)
        if ey_clear != x_ref[EY]:  # a car alongside: hold the offset along the track, not the plan's heading across
            x_ref[EY], x_ref[EPSI] = ey_clear, 0.0
        u_all[0, 0] = self.tracking_control(x0, x_ref, a_ref, ey_bound, top_speed)
        return u_all

    def _clear_of_alongside(self, x0, ey_target: float, others) -> float:
        """A fallback's lateral target ey_target (m) moved so that it is no closer to a car alongside than
        that car is now, or than the collision distance if it is farther: alongside = closer along the
        track than the footprint distance, the arc-length gap measured at the smaller of the two cars'
        local scales 1 - kappa ey (shorter on the inside of a turn, longer on the outside; at least 0.2).
        Why: in a run of failed solves the fallback tracks a plan of the game, which assumed the others
        make room, or after its horizon the reference line's offset at the car, across the track; both
        steered an RD3G car into a car beside it (4-car races on `full` with the racing line,
        `race --track buzzracer:full --line racing --cars rd3g,rd3g,mpc,mpc --seed 1`; 1-vs-3 on the
        oval, `race --cars rd3g,mpc,mpc,mpc --seed 13`)."""
        x0 = np.asarray(x0, dtype=float)
        d, along = self.tm.collision_distance(), self.tm.footprint_distance()
        kappa = float(self.tm.track.curvature(np.mod(x0[S], self.tm.track.length)))
        for s_o, ey_o in others:
            scale = max(min(1.0 - kappa * float(x0[EY]), 1.0 - kappa * float(ey_o)), 0.2)
            gap = float(ey_o) - float(x0[EY])
            if scale * abs(float(s_o) - float(x0[S])) >= along:
                continue
            clear = min(d, abs(gap))
            ey_target = min(ey_target, float(ey_o) - clear) if gap > 0 else max(ey_target, float(ey_o) + clear)
        return ey_target

    def _fallback_reference(self, x0, top_speed: float | None) -> tuple[np.ndarray, float]:
        """(reference state, reference acceleration in m/s^2) of a fallback step: the last plan the
        car used, advanced one control period per fallback step, while that plan still covers the
        present; after its horizon, the track's own reference at the car (the cost's lateral
        reference, heading along the track, the speed cap), at zero acceleration. Why: past its
        horizon the held last state of an old plan is no reference (a plan that ended turning kept
        the car turning, across the infield), and feeding back the previous fallback's acceleration
        as the reference integrated the speed error."""
        c = self.config
        self._reference = self._shifted(self._reference[None])[0]  # set with _prev by every plan _finish keeps
        self._reference_age_s += self.control_period_s
        if self._reference_age_s < c.horizon * c.plan_dt_s:
            ref = self._reference
            return ref[0], float(ref[1, V] - ref[0, V]) / c.plan_dt_s
        x0 = np.asarray(x0, dtype=float)
        stages = self._stages(x0)
        top = self.speed_cap(x0, c.top_speed_mps if top_speed is None else float(top_speed), stages)
        cost = self._cost(top, c.reference_speed_mps, x0, stages)
        stage = cost.x_ref if cost.x_ref_steps is None else cost.x_ref_steps[0]
        x_ref = np.array([x0[S], float(stage[EY]), min(float(stage[V]), top), 0.0])
        return x_ref, 0.0

    def predict_other(self, x_other) -> np.ndarray:
        """(T+1, 2) positions (s, ey) of the other car at constant speed and lateral offset."""
        c = self.config
        t = np.arange(c.horizon + 1) * c.plan_dt_s
        return np.column_stack([x_other[S] + max(float(x_other[V]), 0.0) * t, np.full(t.shape, float(x_other[EY]))])

    def _predicted_other_states(self, x_other) -> np.ndarray:
        """(T+1, 4) states of the constant-speed prediction (heading error 0)."""
        other = self.predict_other(x_other)
        x = np.zeros((self.config.horizon + 1, 4))
        x[:, S], x[:, EY], x[:, V] = other[:, 0], other[:, 1], max(float(x_other[V]), 0.0)
        return x

    def fallback_plan(self, x_self, x_others, error: str) -> Plan:
        """The plan for a step whose planning raised (an invalid problem, a solver error): as for a
        failed solve, the car tracks the last plan it used in closed loop (tracking_control); before the
        first plan, or from a non-finite state, it coasts straight (neutral: zero throttle and zero
        steering command). The other cars are shown at constant speed. Never raises for finite input;
        the next step plans again, warm-started from this step's controls."""
        c = self.config
        x_self = np.asarray(x_self, dtype=float)
        finite = bool(np.all(np.isfinite(x_self)))
        ey_bound = self.tm.ey_bound([x_self[S]]) if finite else math.nan
        if self._prev is not None and finite:
            others = [x[:2] for x in _rows(x_others) if len(x) >= 2 and np.all(np.isfinite(x))]
            u_all = self._track_previous(x_self, ey_bound, others=others)
            u = u_all[0]
            x_prev = self._shifted(self._prev.x)
            x_prev[0] = np.asarray(self.tm.rollout_model(c.plan_dt_s).rollout(x_self, u))
            self._prev = dataclasses.replace(self._prev, u=u_all, x=x_prev,
                                             lam=None if self._prev.lam is None else self._shifted(self._prev.lam))
        else:
            v = float(x_self[V]) if math.isfinite(x_self[V]) else 0.0
            neutral = list(self.mapper.neutral_control(v))
            u = np.tile(neutral, (c.horizon, 1))
        own = (np.asarray(self.tm.rollout_model(c.plan_dt_s).rollout(x_self, u)) if finite
               else np.tile(x_self, (c.horizon + 1, 1)))
        others = [self._predicted_other_states(x) if np.all(np.isfinite(x)) else np.tile(x, (c.horizon + 1, 1))
                  for x in _rows(x_others)]
        return Plan(x=np.stack([own, *others]), u=np.asarray(u), status="error", iterations=0, solve_time_s=0.0,
                    max_violation=math.nan, used="fallback", d_min=math.nan, ey_bound=ey_bound, error=error)

    def _warm_settings_for(self, n_agents: int):
        """The warm settings, with PlannerConfig.max_iter_per_extra_player more iterations per player
        beyond two."""
        extra = max(n_agents - 2, 0) * self.config.max_iter_per_extra_player
        if extra == 0:
            return self._warm_settings
        if n_agents not in self._game_settings:
            base = self.config.solver.get("max_iter", self._warm_settings.max_iter)
            self._game_settings[n_agents] = solver_settings(self.config.solver, {"max_iter": base + extra})
        return self._game_settings[n_agents]

    def _solver_for(self, problem: GameProblem, settings) -> Solver:
        """The planner's solver with this plan's problem and settings: set up at the first plan with this
        many agents, updated (no new set-up) at every later one."""
        n = len(problem.agents) + 1000 * len(problem.obstacles)
        self._solver = self._solvers.get(n)
        if self._solver is None:
            self._solver = self._solvers[n] = Solver(problem, settings)
        else:
            self._solver.update(problem)
            if self._solver.settings is not settings:
                self._solver.update_settings(settings)
        return self._solver

    def _rollout(self, problem: GameProblem, u: np.ndarray) -> np.ndarray:
        model = self.tm.rollout_model(self.config.plan_dt_s)
        return np.stack([np.asarray(model.rollout(np.asarray(a.x0, dtype=float), u[i]))
                         for i, a in enumerate(problem.agents)])

    def _distance_steps(self, d_min: float, nominal: float, rate_factor: float = 1.0):
        """The collision distance for k = 1..T: d_min (relaxed so that k = 1 is feasible) if it equals
        the nominal one or separation_recovery_mps is 0; otherwise d_min at k = 1 and 2, then growing
        at separation_recovery_mps x rate_factor (recovery_rate_factor) per second back to the nominal
        distance (per-step array). The positions at k = 1 and 2 hardly depend on the controls (the first
        control acts on the speed and heading used from k = 1 on), so a ramp from k = 2 made a car closing
        at 0.4 m/s infeasible."""
        rate = self.config.separation_recovery_mps * rate_factor
        if rate <= 0 or d_min >= nominal:
            return d_min
        k = np.arange(1, self.config.horizon + 1)
        return np.minimum(nominal, d_min + rate * self.config.plan_dt_s * np.maximum(k - 2, 0))

    @staticmethod
    def recovery_rate_factor(gap_s: float, gap_ey: float, along_track_scale: float) -> float:
        """The rate (per m/s of recovery) at which the collision constraint's separation |(a ds, dey)|
        grows when a pair's Frenet gap (gap_s, gap_ey) opens along its own direction: the separation over
        the Frenet distance |(ds, dey)|, between a (in line) and 1 (side by side), at most 1. Why: the
        separation ramp (_distance_steps) grows the constraint's measure, in which an along-track gap counts
        a times its length; in the tile turns a is 0.41 (the window's 0.3 m turn), so 0.3 m/s of measure
        asked a pair in line to open the gap at 0.73 m/s, while follow_speed_cap drops the rear car back
        at 0.3 m/s: the ramp's plans were out of reach and RD3G's 4-car solves on `full` fell back in 85 %
        of the plans with such a pair (16 % without). Side by side (and wherever a >= 1, the oval's
        straights) the ramp stays as it was. Used following the racing line; the centre line keeps 1."""
        distance = math.hypot(float(gap_s), float(gap_ey))
        if distance <= 0.0:
            return 1.0
        return min(float(frenet_separation(gap_s, gap_ey, along_track_scale)) / distance, 1.0)

    def _violation(self, problem: GameProblem, x: np.ndarray) -> float:
        """Largest violation (m or m/s) along trajectories x of the agents' track-limit bounds and top speeds
        and of separation (each pair at its own distance, measured as the constraint does): following the
        racing line only our car's (agent 0's) from every other agent and obstacle, on the centre line every
        pair's (its measured races stay as they were). The separations among the other cars are their own
        affair: the game predicts them avoiding each other, but our car's plan keeps its own distance from
        each of their predicted paths whether or not those paths keep theirs. Counting them stopped RD3G
        from using plans that were sound for it: in the 4-car races on `full`, a leading car drove on its
        fallback for 84 plans in a row because the three cars 1-2 m behind it, all in its game, could not
        be planned apart in 15 iterations."""
        worst = 0.0
        for i, a in enumerate(problem.agents):
            worst = max(worst, float(np.max(x[i, 1:, EY] - a.x_max[EY])), float(np.max(a.x_min[EY] - x[i, 1:, EY])),
                        float(np.max(x[i, 1:, V]) - a.x_max[V]))
        n = len(problem.agents)
        scale = 1.0 if problem.collision.pos_x_scale is None else np.asarray(problem.collision.pos_x_scale, dtype=float)
        positions = [x[i, 1:, :2] for i in range(n)]
        d_pair = problem.collision.pair_min_distances(n, problem.horizon) if n > 1 else None
        for i in range(1 if self.line is not None else n):  # the centre line keeps checking every pair
            for j in range(i + 1, n):
                gap = positions[i] - positions[j]
                worst = max(worst, float(np.max(d_pair[i, j] - frenet_separation(gap[:, 0], gap[:, 1], scale))))
            for o in problem.obstacles:  # each obstacle at its own distance
                gap = positions[i] - np.asarray(o.positions)[1:]
                worst = max(worst, float(np.max(o.min_distance - frenet_separation(gap[:, 0], gap[:, 1], scale))))
        return max(worst, 0.0)

    def _usable(self, problem: GameProblem, result: GameResult) -> str:
        """"converged", "accepted" (not converged, but its controls re-simulated with the planning model keep
        the constraints _violation checks within accept_violation_m) or "fallback"."""
        if not np.all(np.isfinite(result.u)):
            return "fallback"
        if result.converged and np.all(np.isfinite(result.x)):
            return "converged"
        x = self._rollout(problem, result.u)
        if np.all(np.isfinite(x)) and self._violation(problem, x) <= self.config.accept_violation_m:
            return "accepted"
        return "fallback"

    def _finish(self, problem: GameProblem, d_min: float, ey_bound: float, ids: tuple = (),
                fallback_top: float | None = None) -> Plan:
        """Solve; a converged solve is used as is. A non-converged one is used only if its controls,
        re-simulated with the planning model (removing any dynamics defect), keep the constraints
        _violation checks within accept_violation_m; otherwise ("fallback") the car tracks the last plan it
        used in closed loop (tracking_control) for this step, at most at fallback_top (m/s; default the
        plan's own speed bound)."""
        warm = self._inside_bounds(problem, self._warm_start(ids))
        # Cold start (first plan, before the race starts): no real-time budget yet, so the solver gets
        # its full globalisation (config.cold_start_solver).
        solver = self._solver_for(problem, self._warm_settings_for(len(problem.agents)) if warm is not None
                                  else self._cold_settings)
        result = solver.solve(warm)
        used = self._usable(problem, result)
        # One retry when the warm start was no usable start. From a warm start that fails at once (line
        # search failed at iteration 0, e.g. a stale fallback plan that now violates a constraint) every
        # later step would start from the same stale plan and fall back too. Following the racing line, also
        # when the solve from it ends unusable (a run of fallbacks starts every solve from the iterate of the
        # last failed one; in the 4-car races on `full` three in four such solves failed again), from
        # closed-loop tracking of the stage references; the better of the two is kept.
        if warm is not None and not result.converged and (used == "fallback" if self.line is not None
                                                          else result.iterations == 0):
            solver.update_settings(self._retry_settings)
            retry = solver.solve(self._tracking_guess(problem, warm))
            retry_used = self._usable(problem, retry)
            if result.iterations == 0 or retry_used != "fallback":
                result, used = retry, retry_used
        finite = bool(np.all(np.isfinite(result.u)))
        # Following the racing line a fallback's next warm start continues from this solve's iterate (the
        # shifted stale plan, held over a run of fallbacks, was no start the solver recovered from).
        from_iterate = finite and self.line is not None
        u_all = result.u
        if used == "fallback":
            if warm is None:  # nothing to track yet: the best the solver found
                u_all = result.u if finite else np.zeros_like(result.u)
            else:
                others = [a.x0[:2] for a in problem.agents[1:]] + [np.asarray(o.positions)[0] for o in problem.obstacles]
                top = problem.agents[0].x_max[V] if fallback_top is None else fallback_top
                u_all = self._track_previous(problem.agents[0].x0, ey_bound, top,
                                             result.u if from_iterate else warm.u, others)
        x = self._rollout(problem, u_all)
        keep_result_lam = used != "fallback" or warm is None or from_iterate or warm.lam is None
        lam = result.lam if keep_result_lam else warm.lam
        # This solve's result is the planner's own (nothing else holds it): keep it as the previous plan.
        result.u, result.x, result.lam = np.asarray(u_all), np.asarray(x), np.asarray(lam)
        self._prev, self._prev_ids = result, tuple(ids)
        if used != "fallback" or warm is None:
            self._reference, self._reference_age_s = np.asarray(x[0]), 0.0
        return Plan(x=np.asarray(x), u=np.asarray(u_all[0]), status=result.status, iterations=result.iterations,
                    solve_time_s=result.solve_time_s, max_violation=result.max_violation, used=used,
                    d_min=float(np.min(d_min)), ey_bound=ey_bound)


class RacingPlanner(_RecedingHorizon):
    """RD3G racing planner: the game of our car (agent 0) and the other cars it plans with (agents 1..M).

    The other cars are modelled with the same cost and car model and their own top speeds (known
    before the race: ``other_tops`` of plan, default `opponent_top_speed_mps` for each)."""

    n_agents = 2

    def __init__(self, track_model: FrenetTrackModel, mapper: CommandMapper, config: PlannerConfig,
                 control_period_s: float, opponent_top_speed_mps: float) -> None:
        super().__init__(track_model, mapper, config, control_period_s)
        self.opponent_top_speed = float(opponent_top_speed_mps)

    def follow_speed_cap(self, x_self, x_others, inside_collision_distance, beside_too: bool = False) -> float:
        """Our car's speed bound for this plan: normally its top speed. In line behind the other car
        (it is ahead in s and the lateral gap |ey gap| is below the clearance W_c = 2 * the
        footprint's lateral half-extent at the allowed yaw + collision_margin_m, so our front can
        hit its back) and already closer than the collision distance (inside_collision_distance:
        d_min had to be relaxed), our car may not gain on it along the track: its progress rate
        v cos(epsi) / (1 - kappa ey) may not exceed the other car's at the current offsets and
        headings (on the inside of a turn equal speeds still close the gap).

        Why: the relaxed d_min follows the separation down step by step, and the game's assumption
        that the other car shares the avoidance (accelerates, moves aside) does not hold for an MPC
        that does not, so the rear car closed in slowly until it hit the other car's back. The bound
        asks for at most 0.2 m/s less than our current speed per plan (2 m/s^2 over the first
        planning step) so it stays reachable; the fallback's speed loop uses it too. "In line" also
        holds when the lateral gap, each car moved along its current heading to the second planning
        step, is below W_c: a car cutting across in front of ours, or ours converging on its line,
        closed in before the current gap counted (1-vs-3 seeds 86 and 99). Lateral moves
        stay free: once the lateral gap reaches W_c (pulling out to pass) or the separation is back
        above the collision distance, the bound is lifted.

        ``beside_too`` (a fallback step's bound): the bound holds at any lateral gap. Why: a fallback tracks a
        stale plan, not a pass the game planned, so it may not gain on a car it is already too close to; two
        RD3G cars side by side whose solves kept failing converged on each other's lines, the rear one still
        gaining, into contact (4-car races on `full` with the racing line, seeds 17 and 68).

        Several other cars (rows of x_others, inside_collision_distance one flag per car or one for
        all): the lowest of the bounds for each."""
        rows = _rows(x_others)
        inside = np.broadcast_to(np.asarray(inside_collision_distance, dtype=bool), (len(rows),))
        return min([self._follow_cap(x_self, x, bool(f), beside_too) for x, f in zip(rows, inside)],
                   default=self.config.top_speed_mps)

    def _follow_cap(self, x_self, x_other, inside_collision_distance: bool, beside_too: bool = False) -> float:
        top = self.config.top_speed_mps
        ahead = float(x_other[S] - x_self[S])
        clearance = 2.0 * self.tm.lateral_half_extent + self.config.collision_margin_m
        # In line now or at the second planning step along the current headings: positions up to k = 2
        # hardly depend on the controls, so a car converging on the other's line is already in line.
        t = 2.0 * self.config.plan_dt_s
        drift = [float(x[V]) * math.sin(float(x[EPSI])) * t for x in (x_self, x_other)]
        gap_now = float(x_other[EY] - x_self[EY])
        in_line = min(abs(gap_now), abs(gap_now + drift[1] - drift[0])) < clearance
        if not (inside_collision_distance and ahead > 0 and (in_line or beside_too)):
            return top
        kappa = self.tm.track.curvature(np.mod([x_self[S], x_other[S]], self.tm.track.length))
        stretch = [1.0 - float(kappa[i]) * float(x[EY]) for i, x in enumerate((x_self, x_other))]
        other_rate = max(float(x_other[V]), 0.0) * math.cos(float(x_other[EPSI])) / max(stretch[1], 0.2)
        # Inside the collision distance, drop back at the rate the plans recover the separation
        # (separation_recovery_mps) rather than hold the gap.
        other_rate = max(other_rate - self.config.separation_recovery_mps, 0.0)
        v_match = other_rate * max(stretch[0], 0.2) / max(math.cos(float(x_self[EPSI])), 0.5)
        return min(top, max(v_match, float(x_self[V]) - _BOUND_DROP_MPS))

    def defend_reference(self, x_self, x_others, ey_bound: float, other_tops=None) -> float | None:
        """Lateral reference (m) while defending, or None. Defending = the other car has the higher
        speed reference (other_tops; ours: preferred_speed; both the top speeds unless set) and is behind us along the track by between defend_min_gap_m and
        defend_distance_m; the reference is then the inside of the turn ahead (sign of the mean
        curvature over defend_lookahead_m), defend_margin_m inside the track-limit bound ey_bound.
        None on a straight with no turn in the lookahead, with defend_distance_m = 0, or when the other
        car is already further inside than ours and less than defend_cross_gap_m behind.

        Why: the open-loop game does not make our car cover. Its lead term depends on the other
        car's plan only through that car's own choice, and with the shared collision multiplier our
        car takes half of the avoidance and drifts out from a car passing on the inside. In the
        front/slow races our car lost, the faster car passed on the inside of a turn while our car
        was 4-9 cm outside the centre line. On the inside of a turn, our car leaves too little room
        for a pass there (d_min between the discs), and the pass around the outside is the longer way.
        From defend_min_gap_m on, the other car's nose is beside ours: pulling in then would turn us
        into its side. Crossing over in front of a car that already has the inside, closer than
        defend_cross_gap_m, is a chop: a 50-race batch (front/slow) had 4 contacts in which the faster
        car ran into our back corner, and 2 in 50 more races (one our fault); without chops, none.

        Several other cars (rows of x_others, top speeds other_tops, default opponent_top_speed_mps):
        our car defends if any of them is such a car, and not if crossing would chop any of them."""
        c = self.config
        rows = _rows(x_others)
        tops = [self.opponent_top_speed] * len(rows) if other_tops is None else list(other_tops)
        behind = [float(x_self[S] - x[S]) for x in rows]
        chasers = [k for k in range(len(rows))
                   if tops[k] > self.preferred_speed and c.defend_min_gap_m < behind[k] < c.defend_distance_m]
        if not chasers:
            return None
        ahead = np.mod(float(x_self[S]) + np.linspace(0.0, c.defend_lookahead_m, 31), self.tm.track.length)
        kappa = float(np.mean(self.tm.track.curvature(ahead)))
        if abs(kappa) < 1e-3:
            return None
        for k in chasers:
            if behind[k] < c.defend_cross_gap_m and math.copysign(1.0, kappa) * float(rows[k][EY] - x_self[EY]) > 0:
                return None  # it already has the inside: crossing in front of it now would be a chop
        return math.copysign(max(ey_bound - c.defend_margin_m, 0.0), kappa)

    def plan(self, x_self, x_others, other_tops=None, other_ids=None, obstacles=None, other_refs=None) -> Plan:
        """x_self, x_others (rows): [s (unwrapped, same origin), ey, v, epsi]; x_self already
        delay-predicted. other_tops: the other cars' top speeds (default opponent_top_speed_mps);
        other_refs: their speed references in their costs (default their top speeds);
        other_ids: names that identify them from plan to plan (warm starts per car, default their rows);
        obstacles: states (rows) of cars avoided at constant speed instead of played with (predict_other)."""
        c = self.config
        rows = _rows(x_others)
        far = [] if obstacles is None or len(obstacles) == 0 else list(_rows(obstacles))
        tops = [self.opponent_top_speed] * len(rows) if other_tops is None else [float(v) for v in other_tops]
        refs = tops if other_refs is None else [float(v) for v in other_refs]
        ids = tuple(range(len(rows))) if other_ids is None else tuple(other_ids)
        s_now = [x_self[S], *(x[S] for x in rows), *(x[S] for x in far)]
        ey_bound = self.tm.ey_bound(s_now)
        limits = self.ey_limits(s_now)
        scale = self.tm.along_track_scale(s_now, [x_self[EY], *(x[EY] for x in rows), *(x[EY] for x in far)])
        d_min = self.tm.collision_distance()
        own_stages = self._stages(x_self)
        other_stages = [self._stages(x, self.line_for(top)) for x, top in zip(rows, tops)]
        own_top = self.path_speed_cap(x_self, self.speed_cap(x_self, c.top_speed_mps, own_stages))
        other_top = [self.speed_cap(x, top, st) for x, top, st in zip(rows, tops, other_stages)]
        own_cost = self._cost(own_top, c.reference_speed_mps, x_self, own_stages)
        defend_ey = self.defend_reference(x_self, rows, ey_bound, refs)
        if defend_ey is not None:  # on the inside of the turn, within the turn's radius limit
            defend_ey = min(max(defend_ey, limits[0] + c.defend_margin_m), limits[1] - c.defend_margin_m)
            self._set_reference(own_cost, EY, defend_ey, c.q_defend)
        nominal_d_min = d_min
        predicted = [self.predict_other(x) for x in far]
        limits, d_min, pair = self._feasible_limits([x_self, *rows], limits, d_min, scale, predicted)
        ey_bound = max(-limits[0], limits[1])
        inside = pair[0, 1:] < nominal_d_min
        top = min(own_top, self.follow_speed_cap(x_self, [*rows, *far], inside))
        fallback_top = min(top, self.follow_speed_cap(x_self, [*rows, *far], inside, beside_too=True))
        agents = [self._agent(x_self, top, limits, own_cost, c.lead_weight),
                  *(self._agent(x, t, limits, self._cost(t, r, x, st), c.lead_weight)
                    for x, t, r, st in zip(rows, other_top, refs, other_stages))]
        # Each pair at its own distance: a pair that starts too close is relaxed (and recovers along the
        # plan), the others keep the nominal one; so does each obstacle.
        n = len(agents)
        where = [np.asarray(x[:2], dtype=float) for x in (x_self, *rows, *far)]
        steps = {(i, j): self._distance_steps(float(pair[i, j]), nominal_d_min,
                                              1.0 if self.line is None else
                                              self.recovery_rate_factor(*(where[i] - where[j]), scale))
                 for i in range(len(pair)) for j in range(i + 1, len(pair)) if pair[i, j] < nominal_d_min}
        collision = Collision(min_distance=nominal_d_min, form="distance", pos_x=S, pos_y=EY,
                              pos_x_scale=[scale] * c.horizon,
                              pair_distances=[PairDistance(agents=ij, min_distance=d) for ij, d in steps.items()
                                              if ij[1] < n])
        problem = GameProblem(dt=c.plan_dt_s, horizon=c.horizon, agents=agents, collision=collision,
                              obstacles=[Obstacle(positions=o, min_distance=steps.get((0, n + k), nominal_d_min))
                                         for k, o in enumerate(predicted)])
        plan = self._finish(problem, self._distance_steps(d_min, nominal_d_min), ey_bound, ids, fallback_top)
        if far:
            plan.x = np.concatenate([plan.x, *(self._predicted_other_states(x)[None] for x in far)], axis=0)
        return plan


class MPCOpponent(_RecedingHorizon):
    """Single-car MPC with the racing cost, avoiding a constant-speed prediction of every other car
    (predict_other), one moving obstacle each."""

    def plan(self, x_self, x_others, other_tops=None, other_ids=None, other_refs=None) -> Plan:
        """x_others: rows [s, ey, v, epsi] of every other car (other_tops, other_ids, other_refs:
        unused, the obstacles are constant-speed predictions)."""
        c = self.config
        rows = _rows(x_others)
        s_now = [x_self[S], *(x[S] for x in rows)]
        limits = self.ey_limits(s_now)
        scale = self.tm.along_track_scale(s_now, [x_self[EY], *(x[EY] for x in rows)])
        d_min = self.tm.collision_distance()
        stages = self._stages(x_self)
        top = self.path_speed_cap(x_self, self.speed_cap(x_self, c.top_speed_mps, stages))
        cost = self._cost(top, c.reference_speed_mps, x_self, stages)
        if c.lead_weight > 0:  # progress reward as a far-away quadratic anchor (module doc)
            self._set_reference(cost, S, float(x_self[S]) + _PROGRESS_ANCHOR_M, c.lead_weight / (2.0 * _PROGRESS_ANCHOR_M))
        others = [self.predict_other(x) for x in rows]
        nominal_d_min = d_min
        # Each obstacle has its own distance: relaxing one car that is too close leaves the others at
        # the nominal distance.
        limits, d_min, pair = self._feasible_limits([x_self], limits, d_min, scale, others)
        steps = [self._distance_steps(float(pair[0, k + 1]), nominal_d_min) for k in range(len(others))]
        problem = GameProblem(dt=c.plan_dt_s, horizon=c.horizon,
                              agents=[self._agent(x_self, top, limits, cost, 0.0)],
                              collision=Collision(min_distance=d_min, form="distance", pos_x=S, pos_y=EY,
                                                  pos_x_scale=[scale] * c.horizon),
                              obstacles=[Obstacle(positions=o, min_distance=d) for o, d in zip(others, steps)])
        plan = self._finish(problem, self._distance_steps(d_min, nominal_d_min), max(-limits[0], limits[1]))
        plan.x = np.concatenate([plan.x, *(self._predicted_other_states(x)[None] for x in rows)], axis=0)
        return plan


def _rows(x_others) -> np.ndarray:
    """The other cars' states as rows (M, 4): one (4,) state is one car."""
    return np.atleast_2d(np.asarray(x_others, dtype=float))
