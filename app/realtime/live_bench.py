"""What a live viewer costs the real-time loop: the same HIL races without and with `--viewer`, one
after the other per seed, the viewer a headless Rerun viewer server this bench starts (`rerun
--serve-grpc`, which receives the stream as a viewer does). Per mode, every tick of every race
pooled from the recordings: the loop's busy time (tick start to command, what the deadline bounds)
and the telemetry stage after it, p50 / p99 / max, and the deadline misses. Writes the live-view
section of docs/benchmarks.md.

    python -m app bench live-view --seeds 4 [--rt-priority 20] [--json runs/live_view_bench.json]
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import time
from pathlib import Path

import numpy as np

from app.cli import UserError
from app.commands import race
from app.live_view import answers, viewer_executable
from bench.report import machine_description, write_section
from fileio import atomic_write_text, check_output_path
from race.recording import load_recording

MODES = ("without", "with")  # --viewer


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--rt-priority", type=int, default=20,
                        help="the HIL races' --rt-priority (default 20, as `race --hil` when permitted; 0 = normal)")
    parser.add_argument("--max-time", type=float, default=10.0, help="race time limit of each race (default 10 s)")
    parser.add_argument("--json", default="runs/live_view_bench.json")
    parser.add_argument("--no-docs", action="store_true", help="do not write docs/benchmarks.md")


def _race_args(seed: int, out: Path, json_path: Path, args, viewer: str | None):
    p = argparse.ArgumentParser()
    race.register(p.add_subparsers())
    argv = ["race", "--hil", "--seed", str(seed), "--rt-priority", str(args.rt_priority), "--max-time",
            str(args.max_time), "--out", str(out), "--json", str(json_path)]
    return p.parse_args(argv + (["--viewer", viewer] if viewer else []))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(args) -> int:
    check_output_path(args.json, stream=True)
    exe = viewer_executable("bench live-view", "install rerun-sdk")
    port = _free_port()
    server = subprocess.Popen([exe, "--serve-grpc", "--port", str(port)], stdin=subprocess.DEVNULL,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    runs = Path("runs/live_view_bench")
    runs.mkdir(parents=True, exist_ok=True)
    races = []
    try:
        deadline = time.monotonic() + 20
        while not answers("127.0.0.1", port, 0.2):
            if time.monotonic() > deadline or server.poll() is not None:
                raise UserError(f"bench live-view: the Rerun server ({exe} --serve-grpc) did not start")
            time.sleep(0.2)
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            for mode in MODES:
                out, js = runs / f"{mode}-seed{seed}.rrd", runs / f"{mode}-seed{seed}.json"
                a = _race_args(seed, out, js, args, url if mode == "with" else None)
                load = os.getloadavg()[0]
                a.func(a)
                busy, telemetry = tick_times(load_recording(out))
                races.append({"seed": seed, "viewer": mode == "with", "load_before": load,
                              "summary": json.loads(js.read_text()), "busy_ms": busy, "telemetry_ms": telemetry})
                print(f"seed {seed} {mode} viewer: {races[-1]['summary']['end_reason']}", flush=True)
    finally:
        server.terminate()
        server.wait(timeout=10)
    atomic_write_text(args.json, json.dumps(races) + "\n", stream=True)
    body = report(races, args, machine_description())
    print(body)
    if not args.no_docs:
        write_section("live-view", body)
    return 0


def tick_times(data) -> tuple[list[float], list[float]]:
    """Per tick of a real-time race recording (matched by control step): busy ms and telemetry-stage ms."""
    rows = [data.entities[e] for e in ("loop/busy_ms", "loop/stage/telemetry_ms")]
    values = [dict(zip(r.control_step.tolist(), (v[0] for v in r.columns["Scalars:scalars"]))) for r in rows]
    steps = sorted(set(values[0]) & set(values[1]))
    return [values[0][k] for k in steps], [values[1][k] for k in steps]


def pooled(races, viewer: bool) -> dict:
    """The ticks of every race of one mode: busy and telemetry percentiles (ms), misses, load."""
    mine = [r for r in races if r["viewer"] == viewer]
    busy = np.concatenate([r["busy_ms"] for r in mine])
    telemetry = np.concatenate([r["telemetry_ms"] for r in mine])
    return {"races": len(mine), "ticks": int(sum(r["summary"]["ticks"] for r in mine)),
            "misses": int(sum(r["summary"]["deadline_misses"] for r in mine)),
            "busy": np.percentile(busy, [50, 99, 100]), "telemetry": np.percentile(telemetry, [50, 99, 100]),
            "tick": np.percentile(busy + telemetry, [50, 99, 100]),
            "load": float(np.mean([r["load_before"] for r in mine]))}


def report(races, args, machine: str) -> str:
    rows = {viewer: pooled(races, viewer) for viewer in (False, True)}
    lines = [
        f"Command: `.venv/bin/python -m app bench live-view --seeds {args.seeds} --first-seed {args.first_seed} "
        f"--rt-priority {args.rt_priority} --max-time {args.max_time:g}` ({time.strftime('%Y-%m-%d %H:%M')}; {machine}). "
        f"HIL races of the same seeds without and with `--viewer` (a local `rerun --serve-grpc`), alternately; every "
        f"tick of every race pooled.",
        "",
        "| viewer | races | ticks | tick (busy + telemetry) p50 / p99 / max ms | busy p50 / p99 ms | telemetry stage p50 / p99 ms | deadline misses | load before |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for viewer, r in rows.items():
        k, b, t = r["tick"], r["busy"], r["telemetry"]
        lines.append(f"| {'with' if viewer else 'without'} | {r['races']} | {r['ticks']} | {k[0]:.2f} / {k[1]:.2f} / "
                     f"{k[2]:.2f} | {b[0]:.2f} / {b[1]:.2f} | {t[0]:.3f} / {t[1]:.3f} | {r['misses']} | {r['load']:.1f} |")
    extra = rows[True]["tick"][1] - rows[False]["tick"][1]
    lines += ["", f"The viewer's cost on the p99 tick time (with minus without): {extra:+.2f} ms (goal < 0.5 ms; "
                  f"meaningful on a quiet host only, load average below 1)."]
    return "\n".join(lines)
