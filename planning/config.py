"""Planner parameters (one typed dataclass; every field validated, errors name the field)."""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields

from solver_cpp import make_settings, merge_settings


LINES = ("centre", "racing")  # PlannerConfig.line


class PlannerConfigError(ValueError):
    """A planner parameter is invalid; the message names the field."""


def solver_settings(*layers: Mapping):
    """The solver's Settings from overrides under its own (grouped) names, a later layer overriding an earlier one
    field by field; a None value means the solver's default (solver_cpp.make_settings names any unknown key or bad
    value)."""
    for layer in layers:
        if not isinstance(layer, Mapping):
            raise ValueError(f"must be a mapping of solver settings, got {type(layer).__name__}")
    return make_settings(**merge_settings(*layers))


@dataclass(frozen=True)
class PlannerConfig:
    """Receding-horizon racing planner settings shared by RD3G and the MPC opponent.

    Costs per planning step (k = 1..T), in the solver's QuadraticCost form:
    q_speed (v - v_ref)^2 + q_lateral (ey - raceline_ey)^2 + q_heading epsi^2
    + r_accel a^2 + r_steer delta^2, minus lead_weight * (own progress - opponent progress);
    v_ref = reference_speed_mps (default top_speed_mps), at most the plan's speed bound. With
    line "racing", raceline_ey and v_ref are the racing line's offset and speed at each stage.
    """

    horizon: int = 10                 # planning steps T
    plan_dt_s: float = 0.1            # planning step (s); the plan covers horizon * plan_dt_s
    top_speed_mps: float = 2.0        # upper speed bound of this car (and its speed reference unless set below)
    # The cost's speed reference when it differs from the top speed (the authors' "preference" speed
    # model, docs/racing.md); None: top_speed_mps. Never above the plan's speed bound.
    reference_speed_mps: float | None = None
    lead_weight: float = 0.5          # Q_d: cost per metre of progress difference per step
    q_speed: float = 1.0              # 1/(m/s)^2
    q_lateral: float = 0.5            # 1/m^2, pulls towards raceline_ey
    q_heading: float = 2.0            # 1/rad^2
    # Cornering: the speed bound of a plan is at most sqrt(max_lateral_accel / |kappa|) for the largest
    # centre-line curvature within the plan's reach (the kinematic planning model has no tyre limit).
    max_lateral_accel_mps2: float = 4.2  # on the centre line; see _RecedingHorizon.corner_speed_cap
    r_accel: float = 0.05             # 1/(m/s^2)^2
    r_steer: float = 1.0              # 1/rad^2
    raceline_ey_m: float = 0.0        # lateral reference (m, left positive) with line "centre"; 0 = centre line
    # The reference the cars race: "centre" = the constant raceline_ey_m and top speed, with the cornering
    # cap on the speed bound; "racing" = the track's racing line (tracks.racing_line) as a stage-varying
    # reference, its offset and speed profile at each horizon stage (planning.reference).
    line: str = "racing"
    # The racing line keeps this much more room to the track-limit bound than the planner's (m): a line
    # on the bound (the minimum-time lines touch it in every turn) left no room for tracking error,
    # and the cars following it left the track (docs/racing.md).
    line_margin_m: float = 0.03
    # Following the racing line, the plan's speed bound also keeps the lateral acceleration on the path of
    # the car's last plan (its steering) within this (m/s^2; _RecedingHorizon.path_speed_cap): the line's
    # speed profile holds on the line's own path, and a car off the line turns tighter.
    path_lateral_accel_mps2: float = 6.0
    track_margin_m: float = 0.03      # extra clearance to the track edge beyond the car's half-extent
    heading_allowance_rad: float = 0.15  # yaw assumed when computing the lateral half-extent of the footprint
    collision_margin_m: float = 0.02  # added to the footprints' circumscribed-circle distance
    # Side by side, the collision constraint keeps the cars' centres at least this far apart (m) when it
    # is more than the footprint distance (2 radii + collision_margin_m, 0.195 m for the default car);
    # along the track it keeps the footprint distance (FrenetTrackModel). 0 = the footprint distance in
    # every direction. With the footprint distance sideways one car could not cover both sides of the
    # oval's 0.45 m of drivable width and the paper's front/slow defence won 7 of 40 races (seeds 0-39), with 0.25 m
    # 32 of 40, neither with a contact (docs/racing.md).
    lateral_clearance_m: float = 0.25
    # When the cars are already closer than the collision distance, the plan's d_min starts at what is
    # feasible at k = 1 and must grow back towards the nominal value at this rate (m/s) over the
    # horizon (per-step d_min); 0 = the relaxed d_min at every step (the plan only may not close in).
    separation_recovery_mps: float = 0.3
    # Defending (RacingPlanner.defend_reference, RD3G only): while a car with a higher top speed is
    # between defend_min_gap_m and defend_distance_m behind along the track, our lateral reference
    # moves to the inside of the turn ahead (mean curvature over defend_lookahead_m), defend_margin_m
    # inside the track-limit bound, with weight q_defend instead of q_lateral. Not when the other car is
    # already further inside than ours and less than defend_cross_gap_m behind. 0 distance = off.
    defend_distance_m: float = 1.0
    defend_min_gap_m: float = 0.2     # closer than this the other car's nose is beside ours: no pull in
    defend_cross_gap_m: float = 0.45  # no crossing to the inside in front of a car already inside of us this close
    defend_lookahead_m: float = 1.5
    defend_margin_m: float = 0.03
    q_defend: float = 5.0             # 1/m^2
    lateral_reach_m: float = 0.1      # lateral motion over a plan assumed when correcting d_min for curvature
    max_brake_mps2: float = 4.0       # planner's braking bound (tyre-limited; the motor could brake harder)
    steering_margin: float = 0.95     # fraction of the steering range the planner may use
    curvature_table_ds_m: float = 0.02
    # Fleet races (race.planning.interacting_cars): an RD3G car's game has at most this many players,
    # itself and the nearest cars that can interact with it; further such cars are constant-speed
    # obstacles, as for MPC (0: every such car is a player). Two: in 4-car races (2 RD3G, 2 MPC, seeds
    # 0-7) two-player games fell back in 1 in 50 plans, four-player games in 1 in 4 and took about twice
    # as long (docs/racing.md, "Fleet races"). Warm-started games of more
    # than two players get max_iter_per_extra_player more solver iterations per extra player: with 15,
    # three- and four-player games stopped at the cap in most plans and the cars fell back.
    game_players: int = 2
    max_iter_per_extra_player: int = 10
    # Solver settings of the warm-started plans, under the solver's own names (solver_cpp Settings; any
    # key not given keeps the solver's default from solver_cpp/include/rd3g/problem.hpp). A deterministic
    # iteration cap rather than a wall-clock limit (time_limit 0: races do not depend on machine speed); the
    # barrier weight is only reduced once its subproblem is nearly solved (rho_progress); no restarts (a
    # restart's result can be worse than the first attempt's), no Levenberg-Marquardt steps, 8 line-search
    # steps; warm starts begin at a smaller barrier weight than a cold solve (with the default 0.01 most of
    # the 15 iterations went into the three barrier reductions; 1e-4 and below stalled: the barrier duals
    # start at zero). The same rules in every attempt (restart_*) and from a deeply overlapping start (deep_overlap
    # > 1: never switched): with the solver's default restart rules and deep_overlap 0.5, `python -m app race` took
    # 11 fallbacks instead of 10, and tests/test_planning.py's closed loop behind a car left the track. Plain
    # halving backtracking (to_crossing off): with the backtracking to just before a crossing, a warm plan on the
    # oval's curve in tests/test_planning.py ended unusable and its fallback left the track limits; not measured
    # on races.
    solver: dict = field(default_factory=lambda: dict(
        max_iter=15, barrier=dict(rho_progress=1.0, rho_init=0.001),
        line_search=dict(max_steps=8, lm_tries=0, to_crossing=False),
        restart=dict(count=0, deep_overlap=2.0, rho_progress=1.0, violation_memory=1, rho_on_stall=False)))
    # The first (cold) plan, computed before the start outside the real-time budget: `solver` with these
    # overrides; None = the solver's own default (here its Levenberg-Marquardt and line-search steps). It starts
    # at the warm plans' barrier weight: from the solver's default 0.01, the cold defending plans of
    # tests/test_planning.py mostly stalled on the outside of the turn (3 of 5 ended right of the centre line, one
    # fell back); from 0.001 all ten of that test's cold plans converge.
    cold_start_solver: dict = field(default_factory=lambda: dict(
        max_iter=200, restart=dict(count=3), line_search=dict(lm_tries=None, max_steps=None)))
    # A non-converged solve is still used if its constraint violation is at most this (m), otherwise
    # the car tracks the previous plan in closed loop (fallback_* gains below).
    accept_violation_m: float = 0.01
    # Fallback tracking law (RacingPlanner/MPCOpponent.tracking_control): Stanley gain on the lateral
    # error (1/s) and speed-loop gain (1/s).
    fallback_lateral_gain: float = 2.0
    fallback_speed_gain: float = 2.0

    def __post_init__(self) -> None:
        positive = {"plan_dt_s", "top_speed_mps", "reference_speed_mps", "max_lateral_accel_mps2", "path_lateral_accel_mps2", "max_brake_mps2", "curvature_table_ds_m", "steering_margin"}
        ints = {"horizon": 1, "game_players": 0, "max_iter_per_extra_player": 0}
        for name in ("solver", "cold_start_solver"):
            try:
                solver_settings(getattr(self, name))
            except (TypeError, ValueError) as exc:
                raise PlannerConfigError(f"planner.{name}: {exc}") from None
        try:
            solver_settings(self.solver, self.cold_start_solver)
        except ValueError as exc:
            raise PlannerConfigError(f"planner.cold_start_solver: {exc}") from None
        for f in fields(self):
            if f.name in ("solver", "cold_start_solver"):
                continue
            if f.name == "line":
                if self.line not in LINES:
                    raise PlannerConfigError(f"planner.line: must be one of {', '.join(LINES)}, got {self.line!r}")
                continue
            v = getattr(self, f.name)
            if f.name == "reference_speed_mps" and v is None:
                continue
            if f.name in ints:
                if isinstance(v, bool) or not isinstance(v, int) or v < ints[f.name]:
                    raise PlannerConfigError(f"planner.{f.name}: must be an integer >= {ints[f.name]}, got {v!r}")
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise PlannerConfigError(f"planner.{f.name}: must be a finite number, got {v!r}")
            if f.name == "raceline_ey_m":
                continue
            if f.name in positive and v <= 0:
                raise PlannerConfigError(f"planner.{f.name}: must be > 0, got {v!r}")
            if v < 0:
                raise PlannerConfigError(f"planner.{f.name}: must be >= 0, got {v!r}")
        if self.game_players == 1:
            raise PlannerConfigError("planner.game_players: must be 0 (every car) or at least 2, got 1")
        if self.steering_margin > 1:
            raise PlannerConfigError(f"planner.steering_margin: must be in (0, 1], got {self.steering_margin!r}")
