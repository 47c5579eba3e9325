"""From a raw drive log to smoothed, uniformly sampled trajectory segments.

Steps (docs/sysid.md, "Preprocessing"): merge duplicate timestamps, split at gaps, resample each
segment onto a uniform grid (commands zero-order hold, measurements linear), then estimate
speed, yaw rate and body-frame velocity with Savitzky-Golay derivatives of the poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_coeffs, savgol_filter

from sysid.log import DriveLog, LogFormatError

GAP_FACTOR = 2.5  # a sampling interval longer than this many nominal periods is a gap
SMOOTHING_WINDOW_S = 0.25  # Savitzky-Golay window (cubic) for poses and their derivatives


@dataclass(frozen=True)
class Trajectory:
    """Uniformly sampled segments of one car, concatenated. Sample k covers [t[k], t[k] + dt)."""

    dt: float
    t: np.ndarray
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


def build_trajectory(log: DriveLog, dt: float | None = None, min_segment_s: float = 1.0) -> Trajectory:
    """Preprocess one car's log (``log`` must hold a single car)."""
    if len(log.cars) != 1:
        raise LogFormatError(f"{log.source}: build_trajectory needs one car, the log has {log.cars}")
    if log.t.size < 3:
        raise LogFormatError(f"{log.source}: too few rows ({log.t.size}) for identification")
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
        hold = np.clip(np.searchsorted(ts, grid + 0.5 * nominal, side="right") - 1, 0, ts.size - 1)
        throttle = m["throttle"][a:b][hold]
        steering = m["steering"][a:b][hold]

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
    return Trajectory(
        dt=nominal,
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
