"""Planners on two cores (docs/racing.md, "Planning several cars on two cores"): the same simulated
fleet races planned in turn (``planner_threads`` 1) and in a pool of threads, one after the other in
the same conditions. Per race and thread count: each planner's wall time per plan (p50 / p99), the
summed CPU time of the cars' plans per control period, the wall time of the whole planning job per
control period, the periods over the control period, and whether the two races were identical.

    python -m app bench planner-threads --cars rd3g,rd3g,rd3g,mpc,mpc,mpc --seeds 0,1,2

Quote the load average it prints with any time."""
from __future__ import annotations

import argparse
import dataclasses
import json
import os

import numpy as np

from fileio import atomic_write_text, check_output_path
from planning.config import LINES

from race.planning import RacePlanners
from race.roster import parse_cars
from race.setup import RaceSpec
from race.simulation import run_race


class TimedPlanners(RacePlanners):
    """RacePlanners keeping every job's wall time and its cars' CPU times (PlanResult.wall_ms, CarPlan.cpu_ms)."""

    def __init__(self, setup, roster=None) -> None:
        super().__init__(setup, roster)
        self.wall_ms: list[float] = []
        self.cpu_ms: list[float] = []

    def plan(self, job):
        result = super().plan(job)
        self.wall_ms.append(result.wall_ms)
        self.cpu_ms.append(sum(cp.cpu_ms for cp in result.cars.values()))
        return result


def measure(setup) -> dict:
    """One race of ``setup``: its outcome (finishing order, lap times, contacts, fallbacks) and times."""
    made = []

    def planners(s):
        made.append(TimedPlanners(s))
        return made[-1]

    load = os.getloadavg()[0]
    s = run_race(setup, planners_cls=planners).summary()
    p = made[0]
    wall, cpu = np.array(p.wall_ms[1:]), np.array(p.cpu_ms[1:])  # without the cold start before the race
    period = 1e3 * setup.control_period_s
    return {"load": load, "outcome": [s["finishing_order"], s["lap_times_s"], s["min_gap_m"], s["collisions"],
                                      s["fallbacks"]],
            "per_car_ms": {c["name"]: (c["solve_ms_p50"], c["solve_ms_p99"]) for c in s["cars"]},
            "cpu_ms": (float(np.percentile(cpu, 50)), float(np.percentile(cpu, 99)), float(cpu.max())),
            "wall_ms": (float(np.percentile(wall, 50)), float(np.percentile(wall, 99)), float(wall.max())),
            "over_period": int(np.sum(wall > period)), "periods": len(wall)}


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--cars", default="rd3g,rd3g,rd3g,mpc,mpc,mpc")
    ap.add_argument("--seeds", default="0", help="comma-separated seeds")
    ap.add_argument("--line", choices=LINES, default=RaceSpec.line,
                    help=f"the planners' reference (race --line; default {RaceSpec.line})")
    ap.add_argument("--threads", type=int, default=2, help="the pool's threads (compared with 1)")
    ap.add_argument("--json", help="write the measurements here")


def run(args) -> int:
    if args.json:
        check_output_path(args.json, stream=True)
    rows = []
    for seed in (int(v) for v in args.seeds.split(",")):
        base = RaceSpec(roster=parse_cars(args.cars), seed=seed, line=args.line).load()
        runs = {n: measure(dataclasses.replace(base, planner_threads=n)) for n in (1, args.threads)}
        for n, r in runs.items():
            print(f"seed {seed}, {n} thread(s), load {r['load']:.1f}: per car p50/p99 ms "
                  + " ".join(f"{k} {a:.1f}/{b:.1f}" for k, (a, b) in r["per_car_ms"].items())
                  + "; per period: CPU p50/p99/max {:.1f}/{:.1f}/{:.1f} ms, wall p50/p99/max {:.1f}/{:.1f}/{:.1f} ms, "
                    .format(*r["cpu_ms"], *r["wall_ms"])
                  + f"over {1e3 * base.control_period_s:.1f} ms in {r['over_period']} of {r['periods']}", flush=True)
        same = runs[1]["outcome"] == runs[args.threads]["outcome"]
        print(f"seed {seed}: races identical: {same}", flush=True)
        rows.append({"seed": seed, "identical": same, "runs": {str(n): r for n, r in runs.items()}})
    if args.json:
        atomic_write_text(args.json, json.dumps(rows, indent=2), stream=True)
    return 0
