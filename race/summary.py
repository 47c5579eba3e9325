"""The race summary shared by every mode's `race --json` record (docs/racing.md, docs/race-stack.md):
the keys every race has, computed one way, and every car's keys (:func:`fleet_keys`). The simulated
race adds its own (clean winner, off-track, fallbacks, ...), the real-time loop its loop statistics; `review --json` recomputes the same numbers
from a recording (race.review.SUMMARY_KEYS)."""
from __future__ import annotations

import numpy as np

RACE_KEYS = ("winner", "lap_times_s", "min_gap_m", "collisions", "solve_ms_p50", "solve_ms_p99", "control_period_ms")


def percentile(values, q: float) -> float | None:
    """The q-th percentile of ``values`` (None when empty)."""
    values = np.asarray(values, dtype=float)
    return float(np.percentile(values, q)) if values.size else None


def race_summary(*, winner, lap_times_s, min_gap_m, collisions: int, solve_ms, control_period_ms: float) -> dict:
    """The RACE_KEYS record; ``solve_ms``: RD3G's planning wall time per plan (ms)."""
    return {"winner": winner, "lap_times_s": lap_times_s, "min_gap_m": min_gap_m, "collisions": collisions,
            "solve_ms_p50": percentile(solve_ms, 50), "solve_ms_p99": percentile(solve_ms, 99),
            "control_period_ms": control_period_ms}


def fleet_keys(results, planners: dict, solve_ms: dict, finish_order, collisions) -> dict:
    """The `race --json` keys of every car (docs/racing.md, "Fleet races"): ``cars`` (roster order),
    ``finishing_order`` and ``collision_events`` (one entry per contact: issue 29 names this list
    ``collisions``, but that key already is the number of contacts, whose meaning is kept)."""
    def pct(name, q):
        return percentile(solve_ms.get(name, ()), q) if name in solve_ms else None

    return {"cars": [{"name": r.name, "planner": planners.get(r.name), "finish_position": r.finish_position,
                      "lap_times_s": r.lap_times_s, "at_fault_collisions": r.at_fault_collisions,
                      "off_track": r.off_track, "solve_ms_p50": pct(r.name, 50), "solve_ms_p99": pct(r.name, 99)}
                     for r in results],
            "finishing_order": list(finish_order),
            "collision_events": [{"cars": list(c.cars), "t_s": c.time_s, "at_fault": c.at_fault} for c in collisions]}
