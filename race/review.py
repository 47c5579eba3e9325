"""Review of a race recording (simulated race or real-time loop): summary numbers and PNG plots.

Everything is recomputed from the recording (race.recording.load_recording), independently of the
running race's state: laps from the logged car positions and footprints by the race's own bookkeeping
(sim.race.LapBookkeeper on the track named in race/setup: line crossings, and progress made off the
track does not count beyond the set-up's allowance), the minimum gap from the logged footprint
rectangles, loop and solver statistics from the logged timings, deadline misses and collisions from
race/events.
"""
from __future__ import annotations

import itertools
import re
from pathlib import Path

import numpy as np

from fileio import atomic_write_with, check_output_dir
from race.recording import EVENTS_ENTITY, RecordingData, car_colors
from race.summary import percentile
from sim.collision import rectangle_gap
from sim.race import OFF_TRACK_ALLOWANCE_CAR_LENGTHS, LapBookkeeper, footprint_excess_m
from tracks import draw_track, load_track

SUMMARY_KEYS = ("laps", "lap_times_s", "min_gap_m", "collisions", "loop_hz_median", "loop_period_p99_ms",
                "deadline_misses", "frames", "solve_ms_p50", "solve_ms_p99", "tracking_error_mm_median",
                "tracking_error_mm_p95", "events")
_SKIPPED = re.compile(r"(\d+) tick\(s\) skipped")
_LAP = re.compile(r"(\S+) lap (\d+) in ")  # race.referee.event_text of a lap


def car_names(data: RecordingData) -> list[str]:
    """The recorded cars, in roster order (RecordingData.roster), then any others by name."""
    names = {e.split("/")[2] for e in data.entities if e.startswith("world/cars/") and e.endswith("/position")}
    order = {c["name"]: i for i, c in enumerate(data.roster())}
    return sorted(names, key=lambda n: (order.get(n, len(order)), n))


def rd3g_cars(data: RecordingData) -> list[str]:
    return [c["name"] for c in data.roster() if c.get("planner") == "rd3g"]


def events(data: RecordingData) -> list[dict]:
    t, texts = data.texts(EVENTS_ENTITY)
    out = []
    for ti, text in zip(t.tolist(), texts):
        kind, _, rest = text.partition(": ")
        out.append({"time_s": round(ti, 4), "kind": kind.strip(), "text": rest.strip()})
    return out


def load_track_of(data: RecordingData):
    name = data.setup().get("track")
    if not name:
        return None
    try:
        return load_track(name)
    except Exception:
        return None


def _track_limits(data: RecordingData, car: str, t: np.ndarray, track):
    """The car's footprint excess (sim.race.footprint_excess_m) at the logged times ``t`` and its
    footprint length (m), from its logged footprint rectangles; None where ``t`` has no footprint."""
    tf, strips = data.strips(f"world/cars/{car}/footprint")
    by_time = {int(k): i for i, k in enumerate(np.round(tf * 1e6).astype(np.int64))
               if strips[i] and len(strips[i][0]) >= 4}
    rows = [by_time.get(int(k)) for k in np.round(t * 1e6).astype(np.int64)]
    if not by_time or any(r is None for r in rows):
        return None, None
    corners = np.array([strips[r][0][:4] for r in rows], dtype=float)
    excess = footprint_excess_m(track, corners)
    length = float(np.median(np.hypot(*(corners[:, 0] - corners[:, 3]).T)))  # front-left to rear-left
    return excess, length


def lap_times(data: RecordingData, track, laps_to_win: int) -> dict[str, list[float]]:
    """Per car: lap times by the race's bookkeeping (sim.race.LapBookkeeper) fed its logged positions
    and footprints (crossings of s = 0, interpolated; the grid rule; progress made off the track does
    not count beyond the race/setup's off_track_allowance_car_lengths). A recording without footprints
    counts every position as on the track. A lap the race completed after the last logged position
    (the simulated race stops logging in the step that decides it) is taken from its `lap` event and
    crossed at the event's time."""
    lap_events = [e for e in events(data) if e["kind"] == "lap"]
    allowance = float(data.setup().get("off_track_allowance_car_lengths", OFF_TRACK_ALLOWANCE_CAR_LENGTHS))
    out = {}
    for car in car_names(data):
        t, pts = data.points(f"world/cars/{car}/position")
        if len(t) < 2:
            out[car] = []
            continue
        xy = np.array([p[0] for p in pts])
        s = np.asarray(track.to_frenet(xy[:, 0], xy[:, 1])[0], dtype=float)
        excess, length = _track_limits(data, car, t, track)
        book = LapBookkeeper(float(track.length), max(int(laps_to_win), 1), s[:1], start_time=float(t[0]),
                             allowance_m=allowance * (length or 0.0))
        for k in range(len(t)):  # the first sample is the grid (only the track limits are judged on it)
            book.update(float(t[k]), s[k:k + 1], None if excess is None else excess[k:k + 1])
        for e in lap_events:
            m = _LAP.match(e["text"])
            if m and m.group(1) == car and e["time_s"] > t[-1] and int(m.group(2)) > book.laps[0]:
                book.cross_line(0, e["time_s"])
        out[car] = [round(float(v), 4) for v in book.lap_times[0]]
    return out


def min_gap(data: RecordingData) -> float | None:
    """The smallest gap between the logged footprints of any two cars at a common time."""
    names = car_names(data)
    if len(names) < 2:
        return None
    series = []
    for car in names:
        t, strips = data.strips(f"world/cars/{car}/footprint")
        keep = [i for i, s in enumerate(strips) if s and len(s[0]) >= 4]
        series.append((np.round(t[keep] * 1e6).astype(np.int64), np.array([strips[i][0][:4] for i in keep])))
    gaps = []
    for (ta, ca), (tb, cb) in itertools.combinations(series, 2):
        common, ia, ib = np.intersect1d(ta, tb, return_indices=True)
        if len(common):
            gaps.append(float(np.min(rectangle_gap(ca[ia], cb[ib]))))
    return min(gaps) if gaps else None


def summarize(data: RecordingData) -> dict:
    """The review record (SUMMARY_KEYS), None where the recording has nothing to say."""
    setup = data.setup()
    track = load_track_of(data)
    evs = events(data)
    laps_to_win = int(setup.get("laps", 1) or 1)
    times = lap_times(data, track, laps_to_win) if track is not None else None
    realtime = data.has("loop/period_ms")
    _, period = data.scalars("loop/period_ms")
    misses = 0
    for e in evs:
        if e["kind"] == "deadline_miss":
            m = _SKIPPED.search(e["text"])
            misses += int(m.group(1)) if m else 1
    solve = np.concatenate([data.scalars(f"planner/{c}/solve_ms")[1] for c in rd3g_cars(data)] or [np.zeros(0)])
    errors = np.concatenate([data.scalars(f"tracking/{c}/error_mm")[1] for c in car_names(data)] or [np.zeros(0)])
    frames = len(data.scalars("camera/latency_ms")[0]) if data.has("camera/latency_ms") else None
    return {
        "laps": {c: len(v) for c, v in times.items()} if times is not None else None,
        "lap_times_s": times,
        "min_gap_m": min_gap(data),
        "collisions": sum(e["kind"] == "collision" for e in evs),
        "loop_hz_median": 1e3 / float(np.median(period)) if realtime and len(period) else None,
        "loop_period_p99_ms": percentile(period, 99) if realtime else None,
        "deadline_misses": misses if realtime else None,
        "frames": frames,
        "solve_ms_p50": percentile(solve, 50),
        "solve_ms_p99": percentile(solve, 99),
        "tracking_error_mm_median": percentile(errors, 50),
        "tracking_error_mm_p95": percentile(errors, 95),
        "events": evs,
    }


def stage_table(data: RecordingData) -> list[tuple[str, float, float, float]]:
    rows = []
    for e in sorted(data.entities):
        if e.startswith("loop/stage/"):
            _, v = data.scalars(e)
            if len(v):
                rows.append((e.split("/")[-1].removesuffix("_ms"), float(np.median(v)), float(np.percentile(v, 99)),
                             float(v.max())))
    return rows


# --------------------------------------------------------------------------- plots
def save_plots(data: RecordingData, folder: Path) -> list[Path]:
    import matplotlib  # here, not at the top: the backend must be chosen before pyplot is imported

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    check_output_dir(folder)
    out = []
    track = load_track_of(data)
    names = car_names(data)
    colors = {name: tuple(v / 255 for v in rgb) for name, rgb in car_colors(names).items()}
    # 1. track with trajectories
    fig, ax = plt.subplots(figsize=(9, 5.6))
    if track is not None:
        draw_track(ax, track)
    for car in names:
        t, pts = data.points(f"world/cars/{car}/position")
        if len(t):
            xy = np.array([p[0] for p in pts])
            ax.plot(xy[:, 0], xy[:, 1], color=colors.get(car, "k"), lw=1.2, label=f"{car} (logged position)")
        t, pts = data.points(f"world/cars/{car}/estimate")
        if len(t):
            xy = np.array([p[0] for p in pts])
            ax.plot(xy[:, 0], xy[:, 1], color=colors.get(car, "k"), lw=0.8, ls="--", label=f"{car} (estimate)")
    for e in events(data):
        if e["kind"] == "collision":
            car = e["text"].split()[0]
            t, pts = data.points(f"world/cars/{car}/position")
            if len(t):
                i = min(np.searchsorted(t, e["time_s"]), len(t) - 1)
                ax.plot(*pts[i][0], "kx", ms=9)
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"{data.path.name}: trajectories (x = collision)")
    out.append(_save(fig, folder / "track.png", plt))
    # 2. speed over time
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 5.6), sharex=True)
    for car in names:
        t, v = data.scalars(f"cars/{car}/speed_mps")
        ax1.plot(t, v, color=colors.get(car, "k"), label=f"{car}")
        t, v = data.scalars(f"cars/{car}/estimated_speed_mps")
        if len(t):
            ax1.plot(t, v, color=colors.get(car, "k"), ls="--", lw=0.8, label=f"{car} (estimate)")
        t, v = data.scalars(f"cars/{car}/command/throttle")
        ax2.step(t, v, where="post", color=colors.get(car, "k"), lw=0.8, label=car)
    ax1.set_ylabel("speed (m/s)")
    ax1.legend(fontsize=8)
    ax2.set_ylabel("throttle command")
    ax2.set_xlabel("race time (s)")
    out.append(_save(fig, folder / "speed.png", plt))
    # 3. timing over time
    fig, ax = plt.subplots(figsize=(9, 4.2))
    solves = [(f"planner/{car}/solve_ms", f"{car} solve") for car in names]
    for entity, label in (("loop/period_ms", "loop period"), ("loop/busy_ms", "loop busy (frame..command)"),
                          ("loop/stage/detect_ms", "detect"), *solves, ("camera/render_ms", "render (HIL, own process)")):
        t, v = data.scalars(entity)
        if len(t):
            ax.plot(t, v, lw=0.8, label=label)
    misses = [e["time_s"] for e in events(data) if e["kind"] == "deadline_miss"]
    if misses:
        ax.plot(misses, np.zeros(len(misses)), "rv", ms=5, label="deadline miss")
    setup = data.setup()
    rate = setup.get("loop", {}).get("rate_hz") if isinstance(setup.get("loop"), dict) else None
    if rate:
        ax.axhline(1e3 / rate, color="grey", ls=":", label="loop period target")
    ax.set_ylabel("ms")
    ax.set_xlabel("race time (s)")
    ax.legend(fontsize=8, ncol=2)
    out.append(_save(fig, folder / "timing.png", plt))
    return out


def _save(fig, path: Path, plt) -> Path:
    fig.tight_layout()
    atomic_write_with(path, lambda tmp: fig.savefig(tmp, dpi=100, format="png"))
    plt.close(fig)
    return path


def format_summary(s: dict, data: RecordingData) -> str:
    def f(v, spec=".2f"):
        return "-" if v is None else format(v, spec)

    setup = data.setup()
    lines = [f"recording: {data.path} ({data.recording_id}); mode {setup.get('mode', 'simulation')}, "
             f"track {setup.get('track', '?')}, seed {setup.get('seed', '?')}"]
    finished = [e for e in s["events"] if e["kind"] == "finished"]
    if finished:
        lines.append(f"winner: {finished[0]['text'].split()[0]} (first to finish)")
    for car, laps in (s["lap_times_s"] or {}).items():
        lines.append(f"  {car:9s} laps {len(laps)}: {', '.join(f'{t:.3f} s' for t in laps) or '-'}")
    lines.append(f"minimum gap between footprints: {f(s['min_gap_m'], '.3f')} m; collisions: {s['collisions']}")
    if s["loop_hz_median"] is not None:
        lines.append(f"loop: median {s['loop_hz_median']:.1f} Hz, period p99 {f(s['loop_period_p99_ms'])} ms, "
                     f"deadline misses {s['deadline_misses']}, frames {s['frames']}")
        for name, p50, p99, mx in stage_table(data):
            lines.append(f"  stage {name:9s} p50 {p50:6.2f} ms  p99 {p99:6.2f} ms  max {mx:6.2f} ms")
    lines.append(f"RD3G solve ({', '.join(rd3g_cars(data)) or 'no RD3G car'}): p50 {f(s['solve_ms_p50'])} ms, "
                 f"p99 {f(s['solve_ms_p99'])} ms")
    if s["tracking_error_mm_median"] is not None:
        lines.append(f"tracking error vs truth: median {s['tracking_error_mm_median']:.2f} mm, "
                     f"p95 {s['tracking_error_mm_p95']:.2f} mm")
    kinds: dict[str, int] = {}
    for e in s["events"]:
        kinds[e["kind"]] = kinds.get(e["kind"], 0) + 1
    lines.append("events: " + ", ".join(f"{k} {v}" for k, v in kinds.items()))
    for e in s["events"]:
        if e["kind"] in ("fault", "recovered", "serial_fault", "fault_injected", "box_failsafe", "collision", "finished",
                         "not_counted"):
            lines.append(f"  {e['time_s']:8.3f} s  {e['kind']}: {e['text']}")
    return "\n".join(lines)
