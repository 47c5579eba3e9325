"""`python -m app bench saddles`: which way of steering away from saddles works, on the game families.

Scan: every (family, cars, seed) solved with `restart_on_saddle` and the passing-order rescue off; the instances
whose first converged attempt is a saddle (status `saddle`) are the cases. Each case is then solved with every
method (solver settings below) at `time_limit` 0 and the default `max_iter`, so that machine load does not decide
the outcome, and judged by the common test of `app bench merge` (bench/merge_bench.record), the solver's
second-order test and, for the first `best_response` cases, an SLSQP best response per player
(bench/verify.best_response_gap). CPU time is the worker process's time for the solve alone."""
from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from bench import merge_bench, verify
from bench.families import family_problem
from solver_cpp import solve

# Solver settings of each method (on top of the C++ defaults, docs/solver.md "Second-order test").
METHODS = {
    "restart": {"second_order": {"escapes": 0, "inertia": 0.0}},  # restart_on_saddle alone (the schedule from the guess)
    "escape": {"second_order": {"escapes": 2, "inertia": 0.0}},   # + restart from the saddle along negative curvature
    "both": {"second_order": {"escapes": 2, "inertia": 1.5}},      # the default: inertia in the escape attempts only
}

Case = tuple[str, int, int]  # (family, cars, seed)


def _scan_one(case: Case) -> tuple[Case, str]:
    # Without restart_on_saddle the first converged attempt ends the schedule; the passing-order rescue, which would
    # run after a schedule that ended at a saddle, is off so that the status is that attempt's.
    r = solve(family_problem(*case), second_order=dict(restart_on_saddle=False), order=dict(candidates=0))
    return case, r.status


def scan(cases: list[Case], workers: int) -> list[Case]:
    """The cases whose first converged attempt is a saddle, in the given order."""
    found = []
    with ProcessPoolExecutor(max_workers=max(1, workers)) as pool:
        for case, status in tqdm(pool.map(_scan_one, cases), total=len(cases), desc="scan", unit="solve"):
            if status == "saddle":
                found.append(case)
    return found


@dataclass
class SaddleRun:
    family: str
    cars: int
    seed: int
    method: str
    status: str
    iterations: int
    attempts: int
    escapes: int
    cpu_s: float
    success: bool            # the common test of app bench merge
    second_order_ok: bool    # not a saddle, every player's smallest eigenvalue >= -SECOND_ORDER_TOL
    best_response_gap: float | None  # largest relative gain of a unilateral SLSQP deviation; None if not run


def _run_one(job: tuple) -> SaddleRun:
    (family, cars, seed), method, best_response = job
    problem = family_problem(family, cars, seed)
    t0 = time.process_time()
    r = solve(problem, **METHODS[method])
    cpu = time.process_time() - t0
    rec = merge_bench.record("rd3g", problem, r, 0.0, cars, seed, family, 1e3 * cpu)
    gap = None
    if best_response:
        gap = max(verify.best_response_gap(problem, r.x, r.u, i, starts=1, seed=seed) for i in range(cars))
    return SaddleRun(family, cars, seed, method, r.status, int(r.iterations), int(r.attempts), int(r.saddle_escapes),
                     cpu, rec.success, bool(rec.second_order_ok), gap)


def compare(cases: list[Case], methods: list[str], workers: int, best_response: int = 0) -> list[SaddleRun]:
    """Every method on every case; the first best_response cases also get the SLSQP best-response test."""
    for m in methods:
        if m not in METHODS:
            raise ValueError(f"unknown method {m!r}; choose from {', '.join(METHODS)}")
    jobs = [(c, m, n < best_response) for n, c in enumerate(cases) for m in methods]
    with ProcessPoolExecutor(max_workers=max(1, workers)) as pool:
        return list(tqdm(pool.map(_run_one, jobs), total=len(jobs), desc="methods", unit="solve"))


def summarize(runs: list[SaddleRun], methods: list[str]) -> list[dict]:
    out = []
    for m in methods:
        rs = [r for r in runs if r.method == m]
        br = [r.best_response_gap for r in rs if r.best_response_gap is not None]
        eq = [r for r in rs if r.success and r.second_order_ok]
        out.append({
            "method": m, "settings": METHODS[m], "cases": len(rs),
            "saddles_left": sum(r.status == "saddle" for r in rs),
            "other_failures": sum(r.status not in ("saddle", "converged") for r in rs),
            "equilibria": len(eq),
            "converged_failing_common_test": sum(r.status == "converged" and not r.success for r in rs),
            "best_response_checked": len(br),
            "best_response_ok": sum(g <= verify.BEST_RESPONSE_TOL for g in br if np.isfinite(g)),
            "iterations_median": float(np.median([r.iterations for r in rs])) if rs else None,
            "iterations_total": int(sum(r.iterations for r in rs)),
            "escapes_total": int(sum(r.escapes for r in rs)),
            "cpu_s_total": float(sum(r.cpu_s for r in rs)),
            "cpu_s_median": float(np.median([r.cpu_s for r in rs])) if rs else None,
        })
    return out


def markdown(summary: list[dict], runs: list[SaddleRun], command: str, machine: str, seconds: float,
             scanned: int | None) -> str:
    """scanned = instances the scan ran over, None if the cases were given."""
    lines = [
        "## Saddles: steering methods compared",
        "",
        f"Command: `{command}` ({seconds:.0f} s). Machine: {machine}.",
        (f"Cases: the {len({(r.family, r.cars, r.seed) for r in runs})} instances (of {scanned} scanned) "
         if scanned else "Cases: the instances given by --cases, ") +
        "whose first converged attempt is a saddle (`restart_on_saddle` and the passing-order rescue off). "
        "Each solved with `time_limit` 0 and the default `max_iter` (1000) per method (settings in bench/saddles.py, "
        "docs/solver.md 'Second-order test'). equilibria = the common test of `app bench merge` and the solver's second-order test; "
        f"best response = SLSQP per player from the result and one perturbed start finds no gain above "
        f"{verify.BEST_RESPONSE_TOL:g} (relative), on the first cases only. CPU = process time of the solves.",
        "",
        "| method | settings | saddles left | other failures | equilibria | converged, failing common test | "
        "best response ok | iterations median / total | escapes | CPU s median / total |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in summary:
        settings = ", ".join(f"{k} {v}" for k, v in s["settings"].items())
        lines.append(f"| {s['method']} | {settings} | {s['saddles_left']}/{s['cases']} | {s['other_failures']} | "
                     f"{s['equilibria']}/{s['cases']} | {s['converged_failing_common_test']} | "
                     f"{s['best_response_ok']}/{s['best_response_checked']} | {s['iterations_median']:.0f} / "
                     f"{s['iterations_total']} | {s['escapes_total']} | {s['cpu_s_median']:.2f} / {s['cpu_s_total']:.1f} |")
    lines += ["", "Per case (status, iterations):", "",
              "| case | " + " | ".join(s["method"] for s in summary) + " |",
              "|---|" + "---|" * len(summary)]
    for case in dict.fromkeys((r.family, r.cars, r.seed) for r in runs):
        cells = []
        for s in summary:
            r = next(r for r in runs if (r.family, r.cars, r.seed) == case and r.method == s["method"])
            ok = "equilibrium" if r.success and r.second_order_ok else r.status
            cells.append(f"{ok}, {r.iterations}")
        lines.append(f"| {case[0]} {case[1]} cars seed {case[2]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
