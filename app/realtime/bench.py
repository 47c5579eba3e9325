"""Race-stack benchmark: the same seeds as a pure simulation and as --hil races of one roster (the
two-car race, or ``--cars`` as `race --cars`); finishing orders and each car's position, RD3G wins,
tracking error, loop rate, deadline misses and the stage breakdown. Writes the loop-bench section of
docs/benchmarks.md.

    .venv/bin/python -m app bench loop --seeds 6 [--cars rd3g,rd3g,mpc,mpc] [--line centre|racing] [--rt-priority 20] [--json runs/loop_bench.json]

The comparison reads each race's `race --json` record by its roster keys (``cars``: name, planner,
finish_position; ``finishing_order``); records written before those keys are two-car races whose RD3G
car is named ``rd3g`` (docs/data/benchmarks-loop.json).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from app import cli
from app.commands import race
from bench.report import machine_description, write_section
from fileio import OutputFileError, atomic_write_text, atomic_write_with, check_output_path
from planning.config import LINES


def _race_args(seed: int, out: str, json_path: str, rt: int, hil: bool, sim_effects: str = "",
               link_protocol: str | None = None, link_capture: str | None = None, camera_profile: str = "realistic",
               cars: str | None = None, line: str | None = None):
    p = argparse.ArgumentParser()
    sub = p.add_subparsers()
    race.register(sub)
    argv = ["race", "--seed", str(seed), "--out", out, "--json", json_path]
    if cars:
        argv += ["--cars", cars]
    if line:
        argv += ["--line", line]
    if hil:
        argv += ["--hil", "--rt-priority", str(rt), "--camera-profile", camera_profile]  # rt 0 = normal scheduling
        if link_protocol:
            argv += ["--link-protocol", link_protocol]
        if link_capture:
            argv += ["--link-capture", link_capture]
    elif sim_effects:
        argv += ["--sim-effects", sim_effects]
    return p.parse_args(argv)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `python -m app bench loop`."""
    parser.add_argument("--seeds", type=int, default=6)
    parser.add_argument("--cars", default=None, metavar="PLANNERS",
                        help="the roster of both races (race --cars, e.g. rd3g,rd3g,mpc,mpc; default: the two-car race)")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--line", choices=LINES, default=None,
                        help="the planners' reference in both races (race --line; default: race's)")
    parser.add_argument("--rt-priority", type=int, default=20,
                        help="the HIL races' --rt-priority (default 20, as `race --hil` when permitted; 0 = normal)")
    parser.add_argument("--sim-effects", default="", metavar="TEXT",
                        help='hidden effects of the pure-simulation reference races (race --sim-effects), e.g. '
                             '"actuation_delay=0.03" to compare HIL with a simulation that has a loop-like delay')
    parser.add_argument("--camera-profile", default="realistic",
                        help="the HIL races' --camera-profile (default realistic: sim/camera_profile.py)")
    parser.add_argument("--link-protocol", default=None, help="the HIL races' --link-protocol (default: race's, rd3g)")
    parser.add_argument("--link-capture", action="store_true",
                        help="write each HIL race's link capture to runs/loop_bench/hil-seed<N>-link.txt")
    parser.add_argument("--json", default="runs/loop_bench.json")
    parser.add_argument("--no-docs", action="store_true", help="do not write docs/benchmarks.md")
    parser.add_argument("--figure", default="docs/figures/loop_bench.png",
                        help="per-seed figure (PNG) written beside the table (default docs/figures/loop_bench.png)")
    parser.add_argument("--replot", metavar="JSON", help="only redraw --figure from a saved --json file")
    parser.add_argument("--pool", nargs="+", metavar="JSON",
                        help="only print the winner distribution pooled over saved --json runs (a 20-seed run's HIL "
                             "win count alone moved from 4 to 10 between two runs of one build)")


def run(args) -> int:
    if args.pool:
        rows = [row for path in args.pool for row in json.loads(Path(path).read_text())]
        d = winner_distribution(rows)
        o = order_agreement(rows)
        print(f"{len(args.pool)} runs, {len(rows)} seed pairs: RD3G won {d['sim_rd3g_wins']} in simulation and "
              f"{d['hil_rd3g_wins']} in HIL; discordant seeds {d['sim_only']} (simulation only) : {d['hil_only']} "
              f"(HIL only), exact McNemar p = {d['mcnemar_p']:.3g}; same finishing order in {o['same_order']}, "
              f"same position for {o['same_position']} of {o['car_pairs']} cars")
        return 0
    if args.replot:
        print(plot(json.loads(Path(args.replot).read_text()), args.figure))
        return 0

    try:  # before the races, not after them
        check_output_path(args.json, stream=True)
        check_output_path(args.figure)
    except OutputFileError as exc:
        parser.error(str(exc))
    runs = Path("runs/loop_bench")
    runs.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        rec = {"seed": seed}
        for mode in ("sim", "hil"):
            out, js = runs / f"{mode}-seed{seed}.rrd", runs / f"{mode}-seed{seed}.json"
            capture = str(runs / f"hil-seed{seed}-link.txt") if args.link_capture and mode == "hil" else None
            a = _race_args(seed, str(out), str(js), args.rt_priority, mode == "hil", args.sim_effects,
                           args.link_protocol, capture, args.camera_profile, args.cars, args.line)
            load0 = os.getloadavg()[0]
            steal0 = steal_seconds()
            t0 = time.monotonic()
            a.func(a)
            rec[mode] = json.loads(js.read_text())
            rec[mode]["wall_s"] = time.monotonic() - t0
            rec[mode]["load_before"] = load0
            rec[mode]["steal_s"] = None if steal0 is None else steal_seconds() - steal0
            print(f"seed {seed} {mode}: finishing order {' > '.join(finishing_order(rec[mode])) or 'none'}", flush=True)
        rows.append(rec)
    atomic_write_text(args.json, json.dumps(rows, indent=2) + "\n", stream=True)
    body = report(rows, args, machine_description())
    print(body)
    print(plot(rows, args.figure))
    if not args.no_docs:
        write_section("loop-bench", body)
    return 0


def steal_seconds() -> float | None:
    """CPU time the hypervisor gave to other guests while ours wanted it (all cores, s; Linux
    /proc/stat 'steal'), None where it is not available. On a shared VM it is what our own scheduling
    cannot control, so the report states it next to the deadline misses."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


# Records from before the roster keys (docs/data/benchmarks-loop.json): the two-car race's RD3G car.
LEGACY_PLANNERS = {"rd3g": "rd3g"}


def planners_of(record: dict) -> dict[str, str]:
    """{car name: planner} of a `race --json` record (module doc)."""
    if "cars" not in record:
        return LEGACY_PLANNERS
    return {c["name"]: c["planner"] for c in record["cars"]}


def finishing_order(record: dict) -> list[str]:
    """The cars that finished, in order (a record without ``finishing_order``: its winner)."""
    if "finishing_order" in record:
        return list(record["finishing_order"])
    return [record["winner"]] if record.get("winner") else []


def positions(record: dict) -> dict[str, int | None]:
    """Each car's finishing position (1-based, None: unfinished); a record without ``cars``: the winner's."""
    if "cars" in record:
        return {c["name"]: c["finish_position"] for c in record["cars"]}
    return {name: k + 1 for k, name in enumerate(finishing_order(record))}


def rd3g_won(record: dict) -> bool:
    """An RD3G car won the race."""
    return record.get("winner") is not None and planners_of(record).get(record["winner"]) == "rd3g"


def order_agreement(rows) -> dict:
    """Simulation against HIL per seed: ``same_order`` (seeds with the same finishing order),
    ``same_winner``, ``same_position`` of ``car_pairs`` (cars with the same finishing position in both,
    unfinished counting as a position) and ``position_shift_mean`` (mean |sim - HIL| position over the
    cars that finished in both; None if none did)."""
    same_order = same_winner = same_position = pairs = 0
    shifts = []
    for r in rows:
        sim, hil = r["sim"], r["hil"]
        same_order += finishing_order(sim) == finishing_order(hil)
        same_winner += sim.get("winner") == hil.get("winner")
        ps, ph = positions(sim), positions(hil)
        for name in set(ps) | set(ph):
            a, b = ps.get(name), ph.get(name)
            pairs += 1
            same_position += a == b
            if a is not None and b is not None:
                shifts.append(abs(a - b))
    return {"same_order": same_order, "same_winner": same_winner, "same_position": same_position,
            "car_pairs": pairs, "position_shift_mean": float(np.mean(shifts)) if shifts else None}


def winner_distribution(rows) -> dict:
    """Wins of an RD3G car in simulation and HIL over the same seeds, and the exact McNemar test on the
    seeds where exactly one mode has an RD3G car winning (paired design: a seed fixes the start). An
    unfinished HIL race counts as not won by RD3G."""
    from scipy.stats import binomtest

    sim = [rd3g_won(r["sim"]) for r in rows]
    hil = [rd3g_won(r["hil"]) for r in rows]
    sim_only = sum(a and not b for a, b in zip(sim, hil))
    hil_only = sum(b and not a for a, b in zip(sim, hil))
    n = sim_only + hil_only
    p = 1.0 if n == 0 else float(binomtest(sim_only, n, 0.5).pvalue)
    reasons: dict[str, int] = {}
    for r in rows:
        reasons[r["hil"].get("end_reason")] = reasons.get(r["hil"].get("end_reason"), 0) + 1
    return {"sim_rd3g_wins": sum(sim), "hil_rd3g_wins": sum(hil), "sim_only": sim_only, "hil_only": hil_only,
            "mcnemar_p": p, "hil_unfinished": sum(r["hil"]["winner"] is None for r in rows), "hil_end_reasons": reasons}


def report(rows, args, machine: str) -> str:
    hil = [r["hil"] for r in rows]
    agree = order_agreement(rows)

    def agg(key):
        v = np.array([h[key] for h in hil if h.get(key) is not None], dtype=float)
        return v

    ticks = sum(h["ticks"] for h in hil)
    misses = sum(h["deadline_misses"] for h in hil)
    lines = [
        f"Command: `.venv/bin/python -m app bench loop --seeds {args.seeds} --first-seed {args.first_seed}"
        + (f" --cars {args.cars}" if getattr(args, "cars", None) else "")
        + (f" --line {args.line}" if getattr(args, "line", None) else "")
        + f" --rt-priority {args.rt_priority} --camera-profile {args.camera_profile}"
        + (f" --sim-effects {args.sim_effects}" if args.sim_effects else "")
        + (f" --link-protocol {args.link_protocol}" if args.link_protocol else "") + "`"
        + f" ({time.strftime('%Y-%m-%d %H:%M')}; {machine}).",
        "",
        f"Scheduling: {'SCHED_FIFO priority ' + str(args.rt_priority) + ' (loop); box 3, planner 4, world 5 and recorder 10 below' if args.rt_priority else 'normal time-sharing'}; "
        f"load average before the HIL races {np.mean([h['load_before'] for h in hil]):.1f} "
        f"(1-minute average: it includes the previous race of this bench; a quiet host reads about 0.5 before the first)"
        + (f"; CPU time stolen by the hypervisor during the HIL races {sum(h['steal_s'] for h in hil):.1f} s "
           f"over {sum(h['wall_s'] for h in hil):.0f} s of wall time (2 cores; per race up to "
           f"{max(h['steal_s'] for h in hil):.2f} s)." if all(h.get('steal_s') is not None for h in hil) else "."),
        "",
        "| seed | sim finishing order | HIL finishing order | HIL loop Hz (median) | period p99 ms | deadline misses | frames (dropped) | tracking error median / p95 mm | detection error median mm | RD3G solve p50 / p99 ms |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    f = lambda v, spec=".1f": "-" if v is None else format(v, spec)  # noqa: E731
    for r in rows:
        h = r["hil"]
        lines.append(
            f"| {r['seed']} | {' > '.join(finishing_order(r['sim'])) or '-'} | {' > '.join(finishing_order(h)) or '-'} "
            f"| {f(h['loop_hz_median'])} | {f(h['loop_period_p99_ms'])} "
            f"| {h['deadline_misses']} / {h['ticks']} | {h['frames']} ({h['frames_dropped']}) "
            f"| {f(h['tracking_error_mm_median'], '.2f')} / {f(h['tracking_error_mm_p95'], '.2f')} "
            f"| {f(h['detection_error_mm_median'], '.3f')} | {f(h['solve_ms_p50'])} / {f(h['solve_ms_p99'])} |")
    d = winner_distribution(rows)
    lines += [
        "",
        f"Same winner in {agree['same_winner']} of {len(rows)} seeds, the same finishing order in "
        f"{agree['same_order']}; {agree['same_position']} of {agree['car_pairs']} cars finished in the same position "
        f"(unfinished counts as one), mean position shift {f(agree['position_shift_mean'], '.2f')} over the cars "
        f"that finished in both. Deadline misses {misses} of {ticks} ticks "
        f"({100 * misses / max(ticks, 1):.2f} %).",
        "",
        f"Winner distribution: an RD3G car won {d['sim_rd3g_wins']} of {len(rows)} in simulation and {d['hil_rd3g_wins']} in HIL; "
        f"HIL races not finished: {d['hil_unfinished']} (end reasons {d['hil_end_reasons']}). Paired by seed, RD3G won in "
        f"simulation only in {d['sim_only']} seeds and in HIL only in {d['hil_only']}; exact McNemar test of equal "
        f"win rates p = {d['mcnemar_p']:.2f} (a small p, e.g. < 0.05, would mean HIL changes who wins).",
        "",
        "Stage breakdown over all HIL ticks (median of the per-race p50 / worst per-race p99, ms); rendering runs in the "
        "world process and is not in the loop budget:",
        "",
        "| stage | p50 | p99 |",
        "|---|---|---|",
    ]
    for stage in ("frame", "detect", "estimate", "plan", "command", "telemetry"):
        p50 = np.median([h["stage_ms_p50"][stage] for h in hil])
        p99 = np.max([h["stage_ms_p99"][stage] for h in hil])
        lines.append(f"| {stage} | {p50:.2f} | {p99:.2f} |")
    lines.append(f"| loop busy (frame..command) | {np.median(agg('busy_ms_p50')):.2f} | {np.max(agg('busy_ms_p99')):.2f} |")
    lines.append(f"| render (world process) | {np.median(agg('render_ms_p50')):.2f} | {np.max(agg('render_ms_p99')):.2f} |")
    lines += ["", f"![loop bench per seed]({Path(args.figure).relative_to('docs') if args.figure.startswith('docs/') else args.figure})"]
    return "\n".join(lines)


def plot(rows, path: str) -> str:
    """Per seed: the winner in simulation and HIL, the HIL race's deadline-miss rate against the 1 % goal,
    and its tracking error (median and p95) against the 10 mm goal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seeds = [r["seed"] for r in rows]
    hil = [r["hil"] for r in rows]
    fig, axes = plt.subplots(3, 1, figsize=(8, 6.5), sharex=True)
    ax = axes[0]
    for k, (mode, marker) in enumerate((("sim", "o"), ("hil", "s"))):
        colours = ["tab:red" if rd3g_won(r[mode]) else "tab:blue" if r[mode].get("winner") else "0.7" for r in rows]
        ax.scatter(seeds, [k + 0.0] * len(seeds), c=colours, marker=marker, s=60)
    ax.set_yticks([0, 1], ["simulation", "HIL"])
    ax.set_ylim(-0.6, 1.6)
    ax.set_title("winner per seed (red: an RD3G car, blue: another car, grey: none)", fontsize=9)
    ax = axes[1]
    ax.bar(seeds, [100 * h["deadline_misses"] / max(h["ticks"], 1) for h in hil], color="0.4")
    ax.axhline(1.0, color="tab:red", ls="--", lw=1, label="goal 1 %")
    ax.set_ylabel("deadline misses (%)")
    ax.legend(fontsize=7)
    ax = axes[2]
    med = [h.get("tracking_error_mm_median") or np.nan for h in hil]
    p95 = [h.get("tracking_error_mm_p95") or np.nan for h in hil]
    ax.plot(seeds, med, "o-", label="median")
    ax.plot(seeds, p95, "^--", label="p95")
    ax.set_yscale("log")
    ax.axhline(10.0, color="tab:red", ls="--", lw=1, label="goal: median < 10 mm")
    ax.set_ylabel("HIL tracking error (mm)")
    ax.set_xlabel("seed")
    ax.set_xticks(seeds)
    ax.legend(fontsize=7)
    fig.tight_layout()
    atomic_write_with(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    plt.close(fig)
    return path


if __name__ == "__main__":  # the old entry point, forwarded
    sys.exit(cli.main(["bench", "loop", *sys.argv[1:]]))
