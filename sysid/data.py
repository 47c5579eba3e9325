"""From raw drive logs (one or several runs) to smoothed, uniformly sampled trajectory segments.

Steps (docs/sysid.md, "Preprocessing"): optionally snap time stamps to the sensor's frame clock,
merge duplicate timestamps, split at gaps, resample each segment onto a uniform grid (commands
zero-order hold, measurements linear), then estimate speed, yaw rate and body-frame velocity with
Savitzky-Golay derivatives of the poses. Several runs become one :class:`Trajectory` whose segments
never cross a run; each run keeps its own time base (``elapsed``: seconds since its first sample), and
the runs are put in a canonical order (by content), so no result depends on the order they were given in.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
from scipy.signal import savgol_coeffs, savgol_filter

from sysid.log import DriveLog, LogFormatError

GAP_FACTOR = 2.5  # a sampling interval longer than this many nominal periods is a gap
SMOOTHING_WINDOW_S = 0.25  # Savitzky-Golay window (cubic) for poses and their derivatives


@dataclass(frozen=True)
class RunInfo:
    """What preprocessing did to one run (reported per run)."""

    source: str
    n_raw_rows: int
    n_duplicates_merged: int  # rows merged into another row's time stamp (or frame, with a frame period)
    n_gaps: int
    n_samples: int
    duration_s: float  # from the first to the last grid sample
    n_missing_frames: int = 0  # with a frame period: frames inside a segment without a row (interpolated)


@dataclass(frozen=True)
class Trajectory:
    """Uniformly sampled segments of one car, concatenated (several runs: run after run, in canonical
    order). Sample k covers [t[k], t[k] + dt); ``t`` is the run's own clock, ``elapsed`` the time since
    the run's first sample."""

    dt: float
    t: np.ndarray
    run: np.ndarray  # run index per sample (into ``runs``)
    elapsed: np.ndarray  # s since the first sample of the sample's run
    runs: tuple[RunInfo, ...]
    segment: np.ndarray  # segment id per sample
    seg_start: np.ndarray  # index of the first sample of the sample's segment
    seg_end: np.ndarray  # index one past the last sample of the sample's segment
    # Measured (resampled) poses.
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray  # unwrapped within a segment
    # Smoothed poses and derivatives (initial states of predictions).
    xs: np.ndarray
    ys: np.ndarray
    headings: np.ndarray
    speed: np.ndarray  # signed: negative when moving backwards
    vx: np.ndarray  # body frame
    vy: np.ndarray
    yaw_rate: np.ndarray
    # Commands sent at t[k], held until t[k+1].
    throttle: np.ndarray
    steering: np.ndarray
    position_noise_m: float  # estimated measurement noise (std per axis)
    heading_noise_rad: float
    speed_from_log: bool
    n_raw_rows: int
    n_duplicates_merged: int
    n_gaps: int

    @property
    def n(self) -> int:
        return self.t.size

    @property
    def n_runs(self) -> int:
        return len(self.runs)

    def blocks(self, idx: np.ndarray, block_s: float) -> np.ndarray:
        """Time-block id of samples ``idx``: blocks of ``block_s`` from each run's start, unique across runs."""
        n_max = int(np.floor(self.elapsed.max() / block_s)) + 1
        return self.run[idx] * n_max + np.floor(self.elapsed[idx] / block_s).astype(int)


def _merge_duplicates(log: DriveLog) -> tuple[dict[str, np.ndarray], int]:
    """Rows with equal t: poses averaged (heading on the circle), commands of the last row."""
    t = log.t
    new_group = np.concatenate([[True], np.diff(t) > 0])
    group = np.cumsum(new_group) - 1
    n_groups = int(group[-1]) + 1
    counts = np.bincount(group, minlength=n_groups).astype(float)

    def mean(v: np.ndarray) -> np.ndarray:
        return np.bincount(group, weights=v, minlength=n_groups) / counts

    last = np.concatenate([np.flatnonzero(new_group)[1:] - 1, [t.size - 1]])
    out = {
        "t": t[new_group],
        "x": mean(log.x),
        "y": mean(log.y),
        "heading": np.arctan2(mean(np.sin(log.heading)), mean(np.cos(log.heading))),
        "throttle": log.throttle[last],
        "steering": log.steering[last],
    }
    # Keep the measured heading itself where there was no duplicate (no round trip through atan2).
    single = counts == 1
    out["heading"][single] = log.heading[new_group][single]
    if log.speed is not None:
        out["speed"] = mean(log.speed)
    return out, int(t.size - n_groups)


def _noise_scale(window: int) -> float:
    """std(measurement - SG fit) = sigma * sqrt(1 - c0) for white noise (c0: centre weight)."""
    c = savgol_coeffs(window, 3)
    return float(np.sqrt(max(1.0 - c[window // 2], 1e-9)))


def snap_to_frames(t: np.ndarray, frame_period: float) -> tuple[np.ndarray, int]:
    """Time stamps snapped to the nearest tick of a frame clock of period ``frame_period`` whose phase is
    the circular mean of the stamps (message arrival times jitter around the sensor's frames). Returns the
    snapped times and the number of frames inside the stretch that no row landed on."""
    phase_angle = np.angle(np.mean(np.exp(2j * np.pi * np.mod(t - t[0], frame_period) / frame_period)))
    phase = t[0] + phase_angle / (2 * np.pi) * frame_period
    frame = np.round((t - phase) / frame_period).astype(np.int64)
    steps = np.diff(np.unique(frame))
    missing = int(np.sum(steps[steps <= GAP_FACTOR] - 1))  # longer holes are gaps, reported as such
    return phase + frame * frame_period, missing


def build_trajectory(log: DriveLog, dt: float | None = None, min_segment_s: float = 1.0,
                     frame_period: float | None = None) -> Trajectory:
    """Preprocess one car's log (``log`` must hold a single car), one run.

    ``frame_period``: the sensor's frame period; time stamps are snapped to its clock (docs/sysid.md,
    "Time stamps"), rows on one frame merged, the grid step is the period."""
    if len(log.cars) != 1:
        raise LogFormatError(f"{log.source}: build_trajectory needs one car, the log has {log.cars}")
    if log.t.size < 3:
        raise LogFormatError(f"{log.source}: too few rows ({log.t.size}) for identification")
    n_missing = 0
    if frame_period is not None:
        if not (np.isfinite(frame_period) and frame_period > 0):
            raise LogFormatError(f"{log.source}: the frame period must be a positive number, got {frame_period!r}")
        snapped, n_missing = snap_to_frames(log.t, frame_period)
        log = replace(log, t=snapped)
        dt = frame_period
    m, n_dup = _merge_duplicates(log)
    t = m["t"]
    steps = np.diff(t)
    median = float(np.median(steps)) if steps.size else 0.0
    if not median > 0:
        raise LogFormatError(f"{log.source}: cannot determine the sampling period (median step {median})")
    gap = steps > GAP_FACTOR * median
    breaks = np.flatnonzero(gap) + 1
    # The grid step is the mean (not the median) interval: a 30 Hz loop on a 1 ms clock logs 33 and
    # 34 ms steps, and a median grid would drift against the log by 1 %.
    nominal = float(np.mean(steps[~gap])) if dt is None else float(dt)
    if not (np.isfinite(nominal) and nominal > 0):
        raise LogFormatError(f"{log.source}: dt must be a positive number, got {nominal!r}")
    bounds = np.concatenate([[0], breaks, [t.size]])

    window = max(5, int(round(SMOOTHING_WINDOW_S / nominal)) | 1)
    cols: dict[str, list[np.ndarray]] = {k: [] for k in (
        "t", "segment", "x", "y", "heading", "xs", "ys", "headings", "speed", "vx", "vy", "yaw_rate",
        "throttle", "steering")}
    pos_res, head_res = [], []
    seg_id = 0
    for a, b in zip(bounds[:-1], bounds[1:]):
        ts = t[a:b]
        if ts[-1] - ts[0] < max(min_segment_s, window * nominal):
            continue
        grid = ts[0] + nominal * np.arange(int(np.floor((ts[-1] - ts[0]) / nominal + 1e-9)) + 1)
        heading_unwrapped = np.unwrap(m["heading"][a:b])
        x = np.interp(grid, ts, m["x"][a:b])
        y = np.interp(grid, ts, m["y"][a:b])
        th = np.interp(grid, ts, heading_unwrapped)
        # Commands are held from the time they were sent. Grid interval k gets the command that is
        # active for most of it (the last one sent before its middle), so timestamp jitter of a
        # fraction of a period does not shift commands by a whole step.
        if log.commands is None:
            hold = np.clip(np.searchsorted(ts, grid + 0.5 * nominal, side="right") - 1, 0, ts.size - 1)
            throttle = m["throttle"][a:b][hold]
            steering = m["steering"][a:b][hold]
        else:  # commands on their own time stamps (the rule is the same)
            cmd = log.commands
            hold = np.clip(np.searchsorted(cmd.t, grid + 0.5 * nominal, side="right") - 1, 0, cmd.t.size - 1)
            throttle, steering = cmd.throttle[hold], cmd.steering[hold]

        def sg(v: np.ndarray, deriv: int = 0) -> np.ndarray:
            return savgol_filter(v, window, 3, deriv=deriv, delta=nominal, mode="interp")

        xs, ys, ths = sg(x), sg(y), sg(th)
        xd, yd, r = sg(x, 1), sg(y, 1), sg(th, 1)
        pos_res.append(np.concatenate([x - xs, y - ys]))
        head_res.append(th - ths)
        c, s = np.cos(ths), np.sin(ths)
        vx = c * xd + s * yd
        vy = -s * xd + c * yd
        if "speed" in m:
            speed_s = np.interp(grid, ts, m["speed"][a:b]) * np.sign(np.where(vx == 0, 1.0, vx))
        else:
            speed_s = np.hypot(xd, yd) * np.sign(np.where(vx == 0, 1.0, vx))
        for k, v in (("t", grid), ("x", x), ("y", y), ("heading", th), ("xs", xs), ("ys", ys), ("headings", ths),
                     ("speed", speed_s), ("vx", vx), ("vy", vy), ("yaw_rate", r),
                     ("throttle", throttle), ("steering", steering)):
            cols[k].append(v)
        cols["segment"].append(np.full(grid.size, seg_id))
        seg_id += 1
    if seg_id == 0:
        raise LogFormatError(
            f"{log.source}: no stretch of the log is long enough (>= {max(min_segment_s, window * nominal):.2f} s "
            f"without a gap longer than {GAP_FACTOR} x the {nominal:.4f} s sampling period)"
        )
    arrays = {k: np.concatenate(v) for k, v in cols.items()}
    segment = arrays.pop("segment")
    starts = np.flatnonzero(np.concatenate([[True], np.diff(segment) != 0]))
    ends = np.concatenate([starts[1:], [segment.size]])
    scale = _noise_scale(window)
    t_grid = arrays["t"]
    info = RunInfo(source=log.source, n_raw_rows=int(log.t.size), n_duplicates_merged=n_dup, n_gaps=int(breaks.size),
                   n_samples=int(t_grid.size), duration_s=float(t_grid[-1] - t_grid[0]), n_missing_frames=n_missing)
    return Trajectory(
        dt=nominal,
        run=np.zeros(t_grid.size, dtype=int),
        elapsed=t_grid - t_grid[0],
        runs=(info,),
        segment=segment,
        seg_start=starts[segment],
        seg_end=ends[segment],
        position_noise_m=float(np.std(np.concatenate(pos_res)) / scale),
        heading_noise_rad=float(np.std(np.concatenate(head_res)) / scale),
        speed_from_log=log.speed is not None,
        n_raw_rows=int(log.t.size),
        n_duplicates_merged=n_dup,
        n_gaps=int(breaks.size),
        **arrays,
    )


def _content_key(log: DriveLog) -> str:
    """A key of a run's content (its rows), so runs can be put in an order that does not depend on how
    they were given."""
    h = hashlib.sha256()
    for a in (log.t, log.x, log.y, log.heading, log.throttle, log.steering):
        h.update(np.ascontiguousarray(a, dtype=float).tobytes())
    return h.hexdigest()


def canonical_order(logs: Sequence[DriveLog]) -> list[int]:
    """Indices of ``logs`` in the canonical (content) order."""
    keys = [_content_key(log) for log in logs]
    return sorted(range(len(logs)), key=lambda i: (keys[i], logs[i].source))


def common_grid_step(logs: Sequence[DriveLog]) -> float:
    """The grid step of a set of runs: the mean of the non-gap intervals pooled over all runs (each run's
    gap threshold from its own median interval)."""
    total, count = 0.0, 0
    for log in logs:
        steps = np.diff(np.unique(log.t))
        if steps.size == 0:
            continue
        keep = steps[steps <= GAP_FACTOR * np.median(steps)]
        total += float(np.sum(np.sort(keep)))  # sorted: the sum does not depend on the row order
        count += keep.size
    if count == 0:
        raise LogFormatError(f"{logs[0].source}: cannot determine the sampling period (fewer than 2 distinct times)")
    return total / count


def build_runs(logs: Sequence[DriveLog], frame_period: float | None = None) -> Trajectory:
    """Several runs of one car as one trajectory on a common grid, in canonical order (docs/sysid.md,
    "Several runs"). Each run is preprocessed on its own (own time base, own gaps and smoothing)."""
    if not logs:
        raise ValueError("build_runs: no runs given")
    order = canonical_order(logs)
    logs = [logs[i] for i in order]
    dt = frame_period if frame_period is not None else (common_grid_step(logs) if len(logs) > 1 else None)
    parts = [build_trajectory(log, dt=dt, frame_period=frame_period) for log in logs]
    if len(parts) == 1:
        return parts[0]
    return concatenate(parts)


def concatenate(parts: Sequence[Trajectory]) -> Trajectory:
    """Runs on the same grid step, one after the other (segment ids, run ids and indices offset)."""
    dt = parts[0].dt
    if any(abs(p.dt - dt) > 1e-12 * dt for p in parts):
        raise ValueError("concatenate: runs must share the grid step")
    arrays = ("t", "elapsed", "x", "y", "heading", "xs", "ys", "headings", "speed", "vx", "vy", "yaw_rate",
              "throttle", "steering")
    out = {k: np.concatenate([getattr(p, k) for p in parts]) for k in arrays}
    offsets = np.cumsum([0] + [p.n for p in parts[:-1]])
    seg_offsets = np.cumsum([0] + [int(p.segment.max()) + 1 for p in parts[:-1]])
    out["segment"] = np.concatenate([p.segment + o for p, o in zip(parts, seg_offsets)])
    out["seg_start"] = np.concatenate([p.seg_start + o for p, o in zip(parts, offsets)])
    out["seg_end"] = np.concatenate([p.seg_end + o for p, o in zip(parts, offsets)])
    out["run"] = np.concatenate([np.full(p.n, i) for i, p in enumerate(parts)])
    weights = np.array([p.n for p in parts], dtype=float)

    def pooled(name: str) -> float:  # RMS over samples
        return float(np.sqrt(np.sum(weights * np.array([getattr(p, name) for p in parts]) ** 2) / weights.sum()))

    return Trajectory(
        dt=dt, runs=tuple(r for p in parts for r in p.runs),
        position_noise_m=pooled("position_noise_m"), heading_noise_rad=pooled("heading_noise_rad"),
        speed_from_log=all(p.speed_from_log for p in parts),
        n_raw_rows=sum(p.n_raw_rows for p in parts), n_duplicates_merged=sum(p.n_duplicates_merged for p in parts),
        n_gaps=sum(p.n_gaps for p in parts), **out,
    )
