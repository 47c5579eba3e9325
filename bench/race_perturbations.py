"""Simulated races under the control-path imperfections of the real-time loop, to see which of them
change who wins (docs/benchmarks.md, HIL loop bench notes): ``python -m app bench race-perturbations``.

Each option perturbs the pure simulation (``race.simulation.run_race``) in one way; without options
the races are the default simulated races. Prints each seed's winner and RD3G's win count.

* ``--late-ms LO HI``: each control period's new command reaches both cars a uniform random LO..HI ms
  late (the previous command acts meanwhile), unknown to the planners.
* ``--tail P A B``: with probability P a command is instead A or B ms late (a solve that missed its
  tick).
* ``--neutral P MS``: with probability P per control period both cars get neutral (zero throttle and
  steering) for MS ms first (a deadline miss of the loop).
* ``--max-iterations N``: RD3G's and the MPC's Newton iteration cap per warm-started plan (``max_iter`` in ``PlannerConfig.solver``, default 15).
* ``--car-params FILE``: e.g. a car file with actuation delays, which the planners compensate.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from fileio import OutputFileError, atomic_write_text, check_output_path
from planning.config import LINES

from race.setup import OPPONENTS, STARTS, RaceSetupError, RaceSpec
from race.simulation import run_race
from sim import Simulator


def perturbed_simulator(late_ms=(0.0, 0.0), tail=(0.0, 0.0, 0.0), neutral=(0.0, 0.0), seed_offset: int = 7919):
    """A Simulator subclass applying each step's commands late / after a neutral pulse (see module doc).
    Delays are whole physics steps and shorter than the control period."""
    lo, hi = (float(v) / 1e3 for v in late_ms)
    p_tail, tail_a, tail_b = float(tail[0]), float(tail[1]) / 1e3, float(tail[2]) / 1e3
    p_neutral, neutral_s = float(neutral[0]), float(neutral[1]) / 1e3

    class PerturbedSimulator(Simulator):
        def __init__(self, *args, **kw):
            super().__init__(*args, **kw)
            self._rng = np.random.default_rng(kw.get("seed", 0) + seed_offset)
            self._previous = np.zeros((self.n_cars, 2))

        def _whole(self, seconds: float, dt_control: float) -> float:
            return min(round(seconds / self.physics_dt) * self.physics_dt, dt_control - self.physics_dt)

        def step(self, commands, dt_control):
            commands = np.asarray(commands, dtype=float)
            if p_neutral > 0 and self._rng.random() < p_neutral:
                first, hold = self._whole(neutral_s, dt_control), np.zeros_like(commands)
            else:
                late = self._rng.choice([tail_a, tail_b]) if p_tail > 0 and self._rng.random() < p_tail \
                    else self._rng.uniform(lo, hi)
                first, hold = self._whole(late, dt_control), self._previous
            self._previous = commands.copy()
            events = list(super().step(hold, first)) if first > 0 else []
            return events + list(super().step(commands, dt_control - max(first, 0.0)))

    return PerturbedSimulator


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `python -m app bench race-perturbations`."""
    parser.add_argument("--track", default=RaceSpec.track, help=f"track name or file (default: {RaceSpec.track})")
    parser.add_argument("--car-params", default=RaceSpec.car_params, help=f"car file (default: {RaceSpec.car_params})")
    parser.add_argument("--opponent", choices=OPPONENTS, default=RaceSpec.opponent)
    parser.add_argument("--rd3g-speed", type=float, default=RaceSpec.rd3g_top_speed_mps, help="RD3G car's top speed (m/s)")
    parser.add_argument("--opponent-speed", type=float, default=RaceSpec.opponent_top_speed_mps, help="opponent's top speed (m/s)")
    parser.add_argument("--control-hz", type=float, default=RaceSpec.control_hz, help="control rate (Hz)")
    parser.add_argument("--line", choices=LINES, default=RaceSpec.line,
                        help=f"the planners' reference (race --line; default {RaceSpec.line})")
    parser.add_argument("--raceline-ey", type=float, default=RaceSpec.raceline_ey_m, metavar="M",
                        help="lateral reference of both cars' racing cost (m, left positive)")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--start", choices=STARTS, default=RaceSpec.start, help="RD3G's start (default: as `race`)")
    parser.add_argument("--late-ms", type=float, nargs=2, default=(0.0, 0.0), metavar=("LO", "HI"))
    parser.add_argument("--tail", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("P", "A_MS", "B_MS"))
    parser.add_argument("--neutral", type=float, nargs=2, default=(0.0, 0.0), metavar=("P", "MS"))
    parser.add_argument("--max-iterations", type=int, default=None)
    parser.add_argument("--rng-seed", type=int, default=7919,
                        help="seed of the perturbations' random draws (added to each race's seed)")
    parser.add_argument("--json", help="write the per-seed winners here")


def run(args) -> int:
    """Races args.seeds seeds under the perturbations; ValueError names a bad option."""
    if not 0 <= args.late_ms[0] <= args.late_ms[1]:
        raise ValueError("--late-ms: need 0 <= LO <= HI")
    for name, p in (("--tail", args.tail[0]), ("--neutral", args.neutral[0])):
        if not 0 <= p <= 1:
            raise ValueError(f"{name}: the probability must be in [0, 1], got {p}")
    if args.json:
        try:
            check_output_path(args.json, stream=True)
        except OutputFileError as exc:
            raise ValueError(str(exc)) from None
    sim_cls = perturbed_simulator(args.late_ms, args.tail, args.neutral, seed_offset=args.rng_seed)
    winners, rd3g_won = {}, {}
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        spec = RaceSpec(track=args.track, car_params=args.car_params, seed=seed, opponent=args.opponent,
                        start=args.start, rd3g_top_speed_mps=args.rd3g_speed, opponent_top_speed_mps=args.opponent_speed,
                        control_hz=args.control_hz, raceline_ey_m=args.raceline_ey, line=args.line)
        try:
            setup = spec.load()
        except RaceSetupError as exc:
            raise ValueError(str(exc)) from None
        if args.max_iterations is not None:
            solver = {**setup.planner.solver, "max_iter": args.max_iterations}
            setup = dataclasses.replace(setup, planner=dataclasses.replace(setup.planner, solver=solver))
        winners[seed] = run_race(setup, simulator_cls=sim_cls).winner
        rd3g_won[seed] = winners[seed] in {car.name for car in setup.cars if car.planner == "rd3g"}
        print(f"seed {seed}: {winners[seed]}", flush=True)
    wins = [s for s, won in rd3g_won.items() if won]
    print(f"RD3G won {len(wins)} of {len(winners)}: seeds {wins}")
    if args.json:
        atomic_write_text(args.json, json.dumps({"argv": sys.argv[1:], "winners": winners}, indent=2) + "\n", stream=True)
    return 0


if __name__ == "__main__":
    raise SystemExit("moved: python -m app bench race-perturbations")
