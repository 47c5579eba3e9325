"""`python -m app batch`: the paper's racing experiment, RD3G vs MPC in a 2x2 grid (RD3G starts in
front/behind x has the higher/lower top speed); win rates beside the paper's (docs/racing.md). With
`--cars` a fleet batch instead: one RD3G car's finishing position against its MPC counterfactual
(app.fleet_batch).

Races run one per task on the local process (`--workers 1`), a local process pool (`--workers N`) or
an existing Dask distributed cluster (`--cluster ADDRESS`, optional extra `cluster`). Every executor
runs the same job tuples through `_one`, so the records are the same for the same seeds."""
from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import pkgutil
import uuid
from pathlib import Path

import numpy as np

from app.cli import UserError
from app.commands.race import FLAGS, add_fleet_arguments, add_race_arguments, make_setup, race_spec, roster_of
from app.fleet_batch import (DEFAULT_FLEET_RACES, FLEET_CELLS, fleet_record, fleet_roster, fleet_table, summarise_fleet,
                             the_rd3g_car)
from app.race_plots import plot_examples
from fileio import atomic_write_text, check_output_dir, check_output_path
from race.setup import PREFERENCE_REFERENCE_MPS, RaceSetupError
from race.simulation import run_race

# Paper (Zhang & Tsiotras, RD3G), physical races RD3G vs MPC: win rate of RD3G per cell.
PAPER_WIN_RATES = {("front", "fast"): 1.0, ("front", "slow"): 0.72, ("rear", "fast"): 0.96, ("rear", "slow"): 0.16}
CELLS = (("front", "fast"), ("front", "slow"), ("rear", "fast"), ("rear", "slow"))
# Seconds to wait for the Dask scheduler to answer (and for it to have a worker) before giving up.
CLUSTER_TIMEOUT_S = 10.0
_WORKERS_WITH_CLUSTER = ("--workers sizes the local process pool and cannot be combined with --cluster; the cluster's "
                         "workers run the races (size them with `dask worker ADDRESS --nworkers N`)")


class RaceFailed(RuntimeError):
    """A race raised an exception (locally or on a cluster worker); the message names its cell and seed."""


def register(sub) -> None:
    p = sub.add_parser("batch", help="RD3G vs MPC win rates in the paper's 2x2 grid (start x top speed)")
    p.add_argument("--races", type=int, default=None,
                   help=f"races per cell (default 200; a fleet batch: {DEFAULT_FLEET_RACES} seeds, each raced twice)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default 1); not with --cluster")
    p.add_argument("--cluster", metavar="ADDRESS",
                   help="run the races on this Dask scheduler (e.g. tcp://host:8786) instead of locally; "
                        "needs the 'cluster' extra here and the project installed on every worker")
    p.add_argument("--cluster-timeout", type=float, default=CLUSTER_TIMEOUT_S,
                   help=f"seconds to wait for the scheduler and a worker (default {CLUSTER_TIMEOUT_S:g})")
    p.add_argument("--max-time", type=float, default=None,
                   help="give up each race after this many seconds of race time (default 60); such races are unfinished")
    p.add_argument("--seed", type=int, default=0, help="first seed; race r of every cell uses seed + r")
    p.add_argument("--json", help="write the per-cell results and one record per race here")
    p.add_argument("--figures", help="write an overtake and a block plot (race_overtake.png, race_block.png) here")
    p.add_argument("--slow-speed", type=float, default=None, help="slow car's top speed (m/s); default rd3g-speed * 0.8")
    add_race_arguments(p)
    add_fleet_arguments(p, roster_file=False, grid_default="random for a fleet batch")
    p.set_defaults(func=run)


def _one(job):
    """Worker: one race -> small picklable record (and the trace if asked for figures)."""
    args, cell, r, fast, slow, keep_trace = job
    if cell in FLEET_CELLS:
        return _fleet_one(args, cell, args.seed + r)
    start, speed = cell
    rd3g, opp = (fast, slow) if speed == "fast" else (slow, fast)
    setup = make_setup(args, args.seed + r, start, rd3g, opp, max_time=args.max_time)
    o = run_race(setup)
    ours, theirs = (c.name for c in sorted(setup.cars, key=lambda c: c.planner != "rd3g"))  # the RD3G car first
    rec = {"cell": cell, "seed": args.seed + r, "winner": o.winner, "rd3g_won": o.winner == ours,
           "collisions": len(o.collisions), "rd3g_at_fault": o.summary()["rd3g_at_fault"],
           "solve_ms": o.solve_ms.astype(np.float32), "min_gap_m": o.min_gap_m, "fallbacks": o.fallbacks,
           "rd3g_off_track": o.off_track[ours], "opponent_off_track": o.off_track[theirs]}
    if keep_trace:
        rec["trace"] = (o.trace_t, o.trace_states, o.trace_progress)
    return rec


def _fleet_setup(args, arm: str, seed: int):
    """The set-up of one fleet race: the --cars roster (the RD3G car swapped to MPC in the
    counterfactual arm), the grid, this seed."""
    spec = race_spec(args, seed, "rear", args.rd3g_speed, args.opponent_speed, max_time=args.max_time)
    try:
        return dataclasses.replace(spec, roster=fleet_roster(spec.roster, arm)).load()
    except RaceSetupError as exc:
        raise UserError(f"{FLAGS.get(exc.field, exc.field)}: {exc.message}") from None


def _fleet_one(args, cell, seed: int) -> dict:
    setup = _fleet_setup(args, cell[1], seed)
    return fleet_record(setup, run_race(setup), cell, seed, the_rd3g_car(roster_of(args)))


def describe_job(job) -> str:
    """'race rear/fast seed 3': which race a job is, for progress and error messages."""
    args, (start, speed), r = job[0], job[1], job[2]
    return f"race {start}/{speed} seed {args.seed + r}"


def _failed(job, exc: BaseException) -> Exception:
    hint = ""
    if isinstance(exc, ImportError):
        hint = " (is the project installed where the race ran? Cluster workers need `pip install .[cluster]` too)"
    return RaceFailed(f"{describe_job(job)} failed: {type(exc).__name__}: {exc}{hint}")


def run_races(jobs, workers: int = 1, cluster: str | None = None,
              cluster_timeout_s: float = CLUSTER_TIMEOUT_S) -> list[dict]:
    """Run `_one` on every job: in this process (workers=1), on a local process pool (workers>1) or on
    the Dask scheduler at `cluster`. Records come back in job order whatever order the races finish in.
    The first race that raises stops the batch with a RaceFailed naming its cell and seed."""
    if cluster is not None:
        if workers != 1:
            raise UserError(_WORKERS_WITH_CLUSTER)
        return _run_on_cluster(jobs, cluster, cluster_timeout_s)
    from tqdm import tqdm

    if workers == 1:
        records = []
        for job in tqdm(jobs, desc="races", unit="race"):
            try:
                records.append(_one(job))
            except Exception as exc:
                raise _failed(job, exc) from exc
        return records
    records = [None] * len(jobs)
    pool = concurrent.futures.ProcessPoolExecutor(max_workers=workers)
    try:
        index = {pool.submit(_one, job): i for i, job in enumerate(jobs)}
        for fut in tqdm(concurrent.futures.as_completed(index), total=len(jobs), desc="races", unit="race"):
            i = index[fut]
            try:
                records[i] = fut.result()
            except Exception as exc:
                raise _failed(jobs[i], exc) from exc
    finally:
        # On a failure, drop the queued races instead of waiting for all of them.
        pool.shutdown(wait=True, cancel_futures=True)
    return records


def _run_on_cluster(jobs, address: str, timeout_s: float) -> list[dict]:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise UserError("--cluster needs Dask distributed, which is not installed: "
                        "pip install .[cluster]  (or pip install 'dask[distributed]')") from None
    from tqdm import tqdm

    _check_scheduler(address, timeout_s)
    client = Client(address, timeout=timeout_s, set_as_default=False)
    with client:
        try:
            client.wait_for_workers(1, timeout=timeout_s)
        except TimeoutError:
            raise UserError(f"--cluster: the scheduler at {address!r} has no workers after {timeout_s:g} s; "
                            f"start some with `dask worker {address}`") from None
        # A worker that cannot unpickle a task (project not installed) drops its connection and Dask then
        # waits forever for another worker, so check the import on every worker first. resolve_name is
        # stdlib, so this probe itself unpickles anywhere.
        probe = client.run(pkgutil.resolve_name, f"{__name__}:_one.__name__", on_error="return")
        broken = {w: r for w, r in probe.items() if isinstance(r, BaseException)}
        if broken:
            worker, exc = sorted(broken.items())[0]
            raise UserError(f"--cluster: {len(broken)} of {len(probe)} workers cannot import the project "
                            f"(e.g. {worker}: {type(exc).__name__}: {exc}); install it on every worker: "
                            "pip install .[cluster]")
        batch = uuid.uuid4().hex[:8]  # unique keys: the scheduler must not reuse another batch's results
        index = {}
        for i, job in enumerate(jobs):
            (start, speed), seed = job[1], job[0].seed + job[2]
            fut = client.submit(_one, job, key=f"race-{start}-{speed}-seed{seed}-{batch}", pure=False)
            index[fut] = i
        records = [None] * len(jobs)
        # set_as_default=False: as_completed must be given the client's loop explicitly.
        for fut in tqdm(as_completed(list(index), loop=client.loop), total=len(jobs), desc="races", unit="race"):
            i = index[fut]
            try:
                records[i] = fut.result()
            except Exception as exc:
                client.cancel(list(index))
                raise _failed(jobs[i], exc) from exc
    return records


def _check_scheduler(address: str, timeout_s: float) -> None:
    """UserError unless a Dask scheduler answers at `address` within `timeout_s`. Dask's own connect
    timeout does not cover its handshake, so a server that accepts the connection but never answers
    (e.g. the dashboard's HTTP port) would block the Client forever: ask for the scheduler's identity
    under one hard deadline first."""
    import asyncio

    from distributed.comm import connect
    from distributed.security import Security

    async def identity():
        # Security() reads Dask's configuration, as the Client does (TLS settings for tls:// addresses).
        comm = await connect(address, timeout=timeout_s, **Security().get_connection_args("client"))
        try:
            await comm.write({"op": "identity", "n_workers": 0, "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    wrong_server = (f"--cluster: {address!r} did not answer like a Dask scheduler ({{}}); give the scheduler's "
                    "address (tcp://HOST:8786 by default, not the dashboard's 8787)")
    try:
        reply = asyncio.run(asyncio.wait_for(identity(), timeout_s))
    except (TimeoutError, asyncio.TimeoutError):  # the same class from Python 3.11 on
        raise UserError(f"--cluster: no Dask scheduler answered at {address!r} within {timeout_s:g} s") from None
    except OSError as exc:  # nothing listening, connection dropped
        raise UserError(f"--cluster: no Dask scheduler answered at {address!r} within {timeout_s:g} s ({exc})") from None
    except ValueError as exc:
        raise UserError(f"--cluster: {address!r} is not a Dask address such as tcp://HOST:8786 ({exc})") from None
    except Exception as exc:  # something else answered with bytes Dask cannot decode
        raise UserError(wrong_server.format(f"{type(exc).__name__}: {exc}")) from None
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        kind = reply.get("type") if isinstance(reply, dict) else type(reply).__name__
        raise UserError(wrong_server.format(f"it is a {kind}"))


def wilson_ci95(wins: int, races: int) -> list[float] | None:
    """95 % Wilson score interval [low, high] of a win rate (None without races)."""
    if races == 0:
        return None
    from scipy.stats import binomtest

    ci = binomtest(int(wins), int(races)).proportion_ci(confidence_level=0.95, method="wilson")
    return [float(ci.low), float(ci.high)]


def summarise(records, races: int) -> list[dict]:
    cells = []
    for start, speed in CELLS:
        rs = [r for r in records if tuple(r["cell"]) == (start, speed)]
        ms = np.concatenate([r["solve_ms"] for r in rs]) if rs else np.zeros(0)
        # Only clean wins count: a car that left the drivable area may have cut the infield.
        wins = sum(r["rd3g_won"] and r["rd3g_off_track"] == 0 for r in rs)
        cells.append({"start": start, "speed": speed, "races": len(rs), "rd3g_wins": int(wins),
                      "win_rate": wins / len(rs) if rs else None,
                      "win_rate_ci95": wilson_ci95(wins, len(rs)),
                      "collisions": int(sum(r["collisions"] for r in rs)),
                      "rd3g_at_fault": int(sum(r["rd3g_at_fault"] for r in rs)),
                      "unfinished": int(sum(r["winner"] is None for r in rs)),
                      "rd3g_off_track_races": int(sum(r["rd3g_off_track"] > 0 for r in rs)),
                      "rd3g_wins_off_track": int(sum(r["rd3g_won"] and r["rd3g_off_track"] > 0 for r in rs)),
                      "opponent_off_track_races": int(sum(r["opponent_off_track"] > 0 for r in rs)),
                      "fallbacks": int(sum(r["fallbacks"] for r in rs)),
                      "control_steps": int(sum(len(r["solve_ms"]) for r in rs)),
                      "solve_ms_p50": float(np.percentile(ms, 50)) if len(ms) else None,
                      "solve_ms_p99": float(np.percentile(ms, 99)) if len(ms) else None})
    return cells


def table(cells) -> str:
    by = {(c["start"], c["speed"]): c for c in cells}
    lines = ["| RD3G car | faster car (ours [95 % interval] / paper) | slower car (ours [95 % interval] / paper) |",
             "|---|---|---|"]
    for start in ("front", "rear"):
        row = [f"starts {'in front' if start == 'front' else 'behind'}"]
        for speed in ("fast", "slow"):
            c = by[(start, speed)]
            lo, hi = c["win_rate_ci95"]
            row.append(f"{c['win_rate']:.2f} [{lo:.2f}, {hi:.2f}] / {PAPER_WIN_RATES[(start, speed)]:.2f} "
                       f"({c['rd3g_wins']}/{c['races']})")
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "Win rate = clean RD3G wins (RD3G never left the track) / races; 95 % Wilson interval.", "",
              "| cell | races | collisions | RD3G at fault | unfinished | RD3G off track (races / wins not counted) "
              "| MPC off track (races) | fallbacks / control steps | planner p50 / p99 (ms) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for c in cells:
        lines.append(f"| {c['start']}/{c['speed']} | {c['races']} | {c['collisions']} | {c['rd3g_at_fault']} | {c['unfinished']} | "
                     f"{c['rd3g_off_track_races']} / {c['rd3g_wins_off_track']} | {c['opponent_off_track_races']} | "
                     f"{c['fallbacks']} / {c['control_steps']} | {c['solve_ms_p50']:.1f} / {c['solve_ms_p99']:.1f} |")
    return "\n".join(lines)


def race_json(rec) -> dict:
    """One race for --json: everything but the per-step planner times (count only) and the trace."""
    start, speed = rec["cell"]
    return {"start": start, "speed": speed, "seed": int(rec["seed"]), "winner": rec["winner"],
            "collisions": int(rec["collisions"]), "rd3g_at_fault": int(rec["rd3g_at_fault"]),
            "min_gap_m": float(rec["min_gap_m"]), "fallbacks": int(rec["fallbacks"]),
            "rd3g_off_track": int(rec["rd3g_off_track"]), "opponent_off_track": int(rec["opponent_off_track"]),
            "control_steps": len(rec["solve_ms"])}


def run(args) -> int:
    if args.races is None:
        args.races = DEFAULT_FLEET_RACES if args.cars else 200
    if args.races < 1:
        raise UserError(f"--races must be at least 1, got {args.races}")
    if args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    if args.cluster is not None and args.workers != 1:
        raise UserError(_WORKERS_WITH_CLUSTER)
    if not args.cluster_timeout > 0:
        raise UserError(f"--cluster-timeout must be positive, got {args.cluster_timeout}")
    if args.max_time is not None and not args.max_time > 0:
        raise UserError(f"--max-time must be positive, got {args.max_time}")
    if args.cars:
        return _run_fleet(args)
    fast = args.rd3g_speed
    slow = args.slow_speed if args.slow_speed is not None else 0.8 * fast
    if not 0 < slow < fast:
        raise UserError(f"--slow-speed must be between 0 and the fast speed {fast}, got {slow}")
    if args.speed_model == "preference" and args.slow_speed is not None:
        raise UserError("--slow-speed: the preference speed model gives both cars the top speed --rd3g-speed "
                        "(the cars differ in their speed references); leave --slow-speed out")
    make_setup(args, 0, "front", fast, slow)  # validate track/car files before starting workers
    if args.json:
        check_output_path(args.json, stream=True)
    if args.figures:
        check_output_dir(args.figures)
    keep = bool(args.figures)
    jobs = [(args, cell, r, fast, slow, keep) for r in range(args.races) for cell in CELLS]
    records = run_races(jobs, args.workers, args.cluster, args.cluster_timeout)
    cells = summarise(records, args.races)
    if args.speed_model == "preference":
        speeds = (f"speed model preference: top speed {fast} m/s for both, speed references / start speeds "
                  f"fast {PREFERENCE_REFERENCE_MPS[0]} m/s, slow {PREFERENCE_REFERENCE_MPS[1]} m/s")
    else:
        speeds = f"speed model limits: top speeds fast {fast} m/s, slow {slow} m/s (ratio {slow / fast:.2f})"
    print(f"\nRD3G vs {args.opponent} on {args.track}: {args.races} races per cell, {speeds}; win rate ours / paper")
    print(table(cells))
    if args.json:
        atomic_write_text(args.json, json.dumps({"speed_model": args.speed_model, "cells": cells,
                                                "races": [race_json(r) for r in records]}, indent=2) + "\n", stream=True)
    if keep:
        for path in plot_examples(records, args, Path(args.figures)):
            print(f"figure: {path}")
    return 0


def _run_fleet(args) -> int:
    """The fleet batch (app.fleet_batch): every seed as given and as its counterfactual."""
    if args.figures:
        raise UserError("--figures: the example plots are of the two-car batch; plot one fleet race with "
                        "`race --cars ... --out RUN.rrd` and `review RUN.rrd --plots DIR`")
    args.grid = args.grid or "random"
    car = the_rd3g_car(roster_of(args))
    for arm in ("rd3g", "counterfactual"):
        _fleet_setup(args, arm, args.seed)  # validate the roster, track and car files before starting workers
    if args.json:
        check_output_path(args.json, stream=True)
    jobs = [(args, cell, r, None, None, False) for r in range(args.races) for cell in FLEET_CELLS]
    records = run_races(jobs, args.workers, args.cluster, args.cluster_timeout)
    fleet = summarise_fleet(records)
    print(f"\nfleet batch on {args.track}: {args.cars}, grid {args.grid}, {args.races} seeds from {args.seed}; "
          f"{car} planned by RD3G vs by MPC")
    print(fleet_table(fleet, car))
    if args.json:
        races = [{k: v for k, v in r.items() if k != "cell"} | {"arm": r["cell"][1]} for r in records]
        atomic_write_text(args.json, json.dumps({"fleet": fleet, "races": races}, indent=2) + "\n", stream=True)
    return 0
