"""`python -m app batch`: the paper's racing experiment, RD3G vs MPC in a 2x2 grid (RD3G starts in
front/behind x has the higher/lower top speed); win rates beside the paper's (docs/racing.md)."""
from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from app.cli import UserError

# Paper (Zhang & Tsiotras, RD3G), physical races RD3G vs MPC: win rate of RD3G per cell.
PAPER_WIN_RATES = {("front", "fast"): 1.0, ("front", "slow"): 0.72, ("rear", "fast"): 0.96, ("rear", "slow"): 0.16}
CELLS = (("front", "fast"), ("front", "slow"), ("rear", "fast"), ("rear", "slow"))


def register(sub) -> None:
    from app.commands.race import add_race_arguments

    p = sub.add_parser("batch", help="RD3G vs MPC win rates in the paper's 2x2 grid (start x top speed)")
    p.add_argument("--races", type=int, default=200, help="races per cell (default 200)")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    p.add_argument("--seed", type=int, default=0, help="first seed; race r of every cell uses seed + r")
    p.add_argument("--json", help="write the per-cell results here")
    p.add_argument("--figures", help="write an overtake and a block plot (race_overtake.png, race_block.png) here")
    p.add_argument("--slow-speed", type=float, default=None, help="slow car's top speed (m/s); default rd3g-speed * 0.8")
    add_race_arguments(p)
    p.set_defaults(func=run)


def _one(job):
    """Worker: one race -> small picklable record (and the trace if asked for figures)."""
    args, cell, r, fast, slow, keep_trace = job
    from app.commands.race import make_setup
    from app.race_runner import run_race

    start, speed = cell
    rd3g, opp = (fast, slow) if speed == "fast" else (slow, fast)
    setup = make_setup(args, args.seed + r, start, rd3g, opp)
    o = run_race(setup)
    rec = {"cell": cell, "seed": args.seed + r, "winner": o.winner, "collisions": len(o.collisions),
           "rd3g_at_fault": sum(c.at_fault == "rd3g" for c in o.collisions), "solve_ms": o.solve_ms.astype(np.float32),
           "min_gap_m": o.min_gap_m, "fallbacks": o.fallbacks,
           "rd3g_off_track": o.off_track["rd3g"], "opponent_off_track": o.off_track["opponent"]}
    if keep_trace:
        rec["trace"] = (o.trace_t, o.trace_states, o.trace_progress)
    return rec


def summarise(records, races: int) -> list[dict]:
    cells = []
    for start, speed in CELLS:
        rs = [r for r in records if tuple(r["cell"]) == (start, speed)]
        ms = np.concatenate([r["solve_ms"] for r in rs]) if rs else np.zeros(0)
        # Only clean wins count: a car that left the drivable area may have cut the infield.
        wins = sum(r["winner"] == "rd3g" and r["rd3g_off_track"] == 0 for r in rs)
        cells.append({"start": start, "speed": speed, "races": len(rs), "rd3g_wins": int(wins),
                      "win_rate": wins / len(rs) if rs else None,
                      "collisions": int(sum(r["collisions"] for r in rs)),
                      "rd3g_at_fault": int(sum(r["rd3g_at_fault"] for r in rs)),
                      "unfinished": int(sum(r["winner"] is None for r in rs)),
                      "rd3g_off_track_races": int(sum(r["rd3g_off_track"] > 0 for r in rs)),
                      "rd3g_wins_off_track": int(sum(r["winner"] == "rd3g" and r["rd3g_off_track"] > 0 for r in rs)),
                      "opponent_off_track_races": int(sum(r["opponent_off_track"] > 0 for r in rs)),
                      "fallbacks": int(sum(r["fallbacks"] for r in rs)),
                      "control_steps": int(sum(len(r["solve_ms"]) for r in rs)),
                      "solve_ms_p50": float(np.percentile(ms, 50)) if len(ms) else None,
                      "solve_ms_p99": float(np.percentile(ms, 99)) if len(ms) else None})
    return cells


def table(cells) -> str:
    by = {(c["start"], c["speed"]): c for c in cells}
    lines = ["| RD3G car | higher top speed (ours / paper) | lower top speed (ours / paper) |", "|---|---|---|"]
    for start in ("front", "rear"):
        row = [f"starts {'in front' if start == 'front' else 'behind'}"]
        for speed in ("fast", "slow"):
            c = by[(start, speed)]
            row.append(f"{c['win_rate']:.2f} / {PAPER_WIN_RATES[(start, speed)]:.2f} ({c['rd3g_wins']}/{c['races']})")
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", "Win rate = clean RD3G wins (RD3G never left the track) / races.", "",
              "| cell | races | collisions | RD3G at fault | unfinished | RD3G off track (races / wins not counted) "
              "| MPC off track (races) | fallbacks / control steps | planner p50 / p99 (ms) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for c in cells:
        lines.append(f"| {c['start']}/{c['speed']} | {c['races']} | {c['collisions']} | {c['rd3g_at_fault']} | {c['unfinished']} | "
                     f"{c['rd3g_off_track_races']} / {c['rd3g_wins_off_track']} | {c['opponent_off_track_races']} | "
                     f"{c['fallbacks']} / {c['control_steps']} | {c['solve_ms_p50']:.1f} / {c['solve_ms_p99']:.1f} |")
    return "\n".join(lines)


def run(args) -> int:
    from tqdm import tqdm

    if args.races < 1:
        raise UserError(f"--races must be at least 1, got {args.races}")
    if args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    fast = args.rd3g_speed
    slow = args.slow_speed if args.slow_speed is not None else 0.8 * fast
    if not 0 < slow < fast:
        raise UserError(f"--slow-speed must be between 0 and the fast speed {fast}, got {slow}")
    from app.commands.race import make_setup
    make_setup(args, 0, "front", fast, slow)  # validate track/car files before starting workers
    keep = bool(args.figures)
    jobs = [(args, cell, r, fast, slow, keep) for r in range(args.races) for cell in CELLS]
    records = []
    if args.workers == 1:
        for job in tqdm(jobs, desc="races", unit="race"):
            records.append(_one(job))
    else:
        with ProcessPoolExecutor(max_workers=args.workers) as pool:
            for rec in tqdm(pool.map(_one, jobs, chunksize=1), total=len(jobs), desc="races", unit="race"):
                records.append(rec)
    cells = summarise(records, args.races)
    print(f"\nRD3G vs {args.opponent} on {args.track}: {args.races} races per cell, top speeds fast {fast} m/s, "
          f"slow {slow} m/s (ratio {slow / fast:.2f}); win rate ours / paper")
    print(table(cells))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"cells": cells}, indent=2) + "\n")
    if keep:
        from app.race_plots import plot_examples
        for path in plot_examples(records, args, Path(args.figures)):
            print(f"figure: {path}")
    return 0
