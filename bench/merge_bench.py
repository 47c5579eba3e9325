"""`python -m app bench merge`: RD3G, iLQGames and ALGames on the same merging instances, one harness.

Every solver gets the same instances and time limit; success is decided here, by one common test on
the returned trajectories (bench/verify.py), not by the solvers' own status."""
from __future__ import annotations

import math
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bench import baselines, verify
from fileio import atomic_write_with
from bench.families import TUNED_FAMILIES, family_problem
from bench.merging import MAIN_LANE_Y, MERGE_LANE_Y, lane_counts, merging_problem
from solver_cpp import solve
from solver_cpp.best_response import best_response_guess

PAPER_MS = {  # Table I of the paper (mean ms over converged runs, i7-7700K)
    "rd3g": {2: 18, 3: 29, 4: 83, 5: 137, 6: 226, 7: 339, 8: 430},
    "algames": {2: 48, 3: 95, 4: 198, 5: 366, 6: 653, 7: 1103, 8: 1833},
    "ilqgames": {2: 324, 3: 505, 4: 657, 5: 829, 6: 1037, 7: 2253, 8: None},  # None: no convergence
}
SOLVERS = ("rd3g", "ilqgames", "algames")

# Common success test (applied to every solver's output).
DYNAMICS_TOL = 1e-6  # state units
COLLISION_TOL_M = 1e-3  # m
STATIONARITY_REL_TOL = 1e-3  # per-player KKT residual / cost-gradient scale (bench/verify.py)
ACTIVE_GAP_M = 1e-2  # a collision constraint counts as active when the gap is within this of d_min
SECOND_ORDER_TOL = 1e-6  # smallest reduced-Hessian eigenvalue accepted (the solver's own test is relative to scale)


def run_solver(name: str, problem, time_limit_s: float, best_response_rounds: int = 0, max_iter: int | None = None,
               settings: tuple = ()):
    """The solver's result and the wall time of any initial-guess work before it (s). time_limit_s <= 0: no time
    limit; max_iter (RD3G only): its iteration budget (None: the solver's default); settings (RD3G only): (name, value)
    overrides of its other settings."""
    if name == "rd3g":
        import time

        budget = dict(settings)
        if max_iter is not None:
            budget["max_iter"] = max_iter
        if best_response_rounds <= 0:
            return solve(problem, time_limit=max(time_limit_s, 0.0), **budget), 0.0
        t0 = time.perf_counter()
        # The solver's own sweeps with its settings: single-agent solves of at most best_response_max_iter iterations
        # and one restart each (a guess, not an answer).
        guess = best_response_guess(problem, best_response_rounds, **dict(settings))
        setup_s = time.perf_counter() - t0
        left = max(time_limit_s - setup_s, 1e-6) if time_limit_s > 0 else 0.0
        return solve(problem, time_limit=left, warm_start=guess, **budget), setup_s

    if name == "ilqgames":
        return baselines.solve_ilqgames(problem, time_limit=time_limit_s), 0.0
    if name == "algames":
        return baselines.solve_algames(problem, time_limit=time_limit_s), 0.0
    raise ValueError(f"unknown solver {name!r}; choose from {SOLVERS}")


@dataclass
class RunRecord:
    solver: str
    cars: int
    seed: int
    status: str
    solve_ms: float
    iterations: int
    success: bool
    failure: str
    active_collision: bool
    min_slack_m: float  # smallest distance - d_min over all pairs and steps
    family: str = "authors"
    # RD3G's second-order test (Info::second_order): every agent's reduced Hessian is positive definite there.
    # None for solvers that do not report it.
    second_order_ok: bool | None = None
    # CPU time of this worker process (time.process_time) around the solve and any best-response guess: unlike
    # solve_ms (wall), it does not grow with the machine's load.
    cpu_ms: float = float("nan")
    # Failures only (successes are feasible by their own point): verify.problem_feasibility's 'infeasible' (proven),
    # 'feasible' (a verified point exists) or 'unknown', with its reason; "" for a success.
    feasibility: str = ""
    feasibility_detail: str = ""
    # With Job.best_response_check >= 0, successes only: the largest relative cost decrease any one player finds by
    # deviating alone (bench/verify.best_response_gap, SLSQP); NaN if no feasible point was found; None if not run.
    best_response_gap: float | None = None


@dataclass(frozen=True)
class Job:
    solver: str
    cars: int
    seed: int
    time_limit_s: float  # <= 0: none
    family: str = "authors"
    best_response_rounds: int = 0
    max_iter: int | None = None  # RD3G's iteration budget; None: its default
    settings: tuple = ()  # RD3G's setting overrides, (name, value) pairs
    repeats: int = 1  # runs of a short solve; the fastest one's times are kept (REPEAT_BELOW_MS)
    best_response_check: int = -1  # >= 0: check each success by SLSQP best responses from it and this many perturbations
    steering_bound: float = math.inf  # rad: every car's |delta| bounded at it too (bench.families.family_problem)


# A solve that stays far from its time limit (or has none) is deterministic, so running it again changes only its
# timing. On the shared machine that noise is additive (other processes, CPU steal) and is largest, relative to the
# solve, on sub-millisecond solves; the fastest of a few runs is the best estimate of a solve's own cost (as Python's
# timeit takes the minimum). Solves slower than this, or than a tenth of their time limit, are run once: the noise
# is a small part of them, repeats would be costly, and a limit near enough to bind could change the result.
REPEAT_BELOW_MS = 200.0


def failure_feasibility(problem, x: np.ndarray, u: np.ndarray) -> tuple[str, str]:
    """Feasibility of an instance a solver failed on (bench/verify.py, problem_feasibility): the solver's returned
    point counts if it violates nothing by more than COLLISION_TOL_M; otherwise the exact fixed-state check, then
    the SLSQP search from zero controls, the returned controls and two seeded starts."""
    if np.all(np.isfinite(x)) and np.all(np.isfinite(u)) and verify.dynamics_defect(problem, x, u) <= DYNAMICS_TOL \
            and max(verify.max_collision_violation_m(problem, x), verify.max_bound_violation(problem, x, u)) <= COLLISION_TOL_M:
        return "feasible", "the solver's own point is feasible"
    rep = verify.problem_feasibility(problem, starts=[u] if np.all(np.isfinite(u)) else [], tol_m=COLLISION_TOL_M)
    return rep.status, rep.detail


def one_run(job: Job) -> RunRecord:
    import time

    problem = family_problem(job.family, job.cars, job.seed, job.steering_bound)
    best = None
    for run in range(job.repeats):
        cpu0 = time.process_time()
        r, setup_s = run_solver(job.solver, problem, job.time_limit_s, job.best_response_rounds, job.max_iter,
                                job.settings)
        cpu_ms = 1e3 * (time.process_time() - cpu0)
        if best is not None and (r.status, r.iterations) != (best[0].status, best[0].iterations):
            raise RuntimeError(f"{job.solver} on {job.family} {job.cars} cars seed {job.seed} is not deterministic: "
                               f"run {run + 1} ended {r.status} after {r.iterations} iterations, run 1 "
                               f"{best[0].status} after {best[0].iterations}")
        if best is None or cpu_ms < best[2]:
            best = (r, setup_s, cpu_ms)
        if cpu_ms >= REPEAT_BELOW_MS or (job.time_limit_s > 0 and cpu_ms >= 100.0 * job.time_limit_s):
            break
    r, setup_s, cpu_ms = best
    rec = record(job.solver, problem, r, setup_s, job.cars, job.seed, job.family, cpu_ms)
    if rec.success and job.best_response_check >= 0:
        rec.best_response_gap = best_response_gap(problem, r, job.best_response_check, job.seed)
    return rec


def best_response_gap(problem, r, starts: int, seed: int) -> float:
    """The largest relative cost decrease any player finds by deviating alone from result r (SLSQP over its own
    controls, the others fixed, from r and `starts` seeded perturbations of it; bench/verify.py): an equilibrium
    check independent of the solver's own tests. NaN if some player's search found no feasible point."""
    gaps = [verify.best_response_gap(problem, np.asarray(r.x), np.asarray(r.u), i, starts=starts, seed=seed)
            for i in range(problem.num_agents)]
    return float("nan") if np.any(np.isnan(gaps)) else float(np.max(gaps))


def record(name: str, problem, r, setup_s: float, cars: int, seed: int, family: str,
           cpu_ms: float = float("nan")) -> RunRecord:
    """The common test (dynamics, controls inside their models' domains, collision violation, per-player
    stationarity), the feasibility of a failure and the second-order verdict of a solver's result r on problem;
    setup_s = initial-guess wall time before the solve (s), cpu_ms = the CPU time of both."""
    x, u = np.asarray(r.x), np.asarray(r.u)
    failure = ""
    defect = verify.dynamics_defect(problem, x, u)
    viol = verify.max_collision_violation_m(problem, x)
    gaps = verify.collision_gaps_m(problem, x)
    if not np.all(np.isfinite(x)) or not np.all(np.isfinite(u)):
        failure = "non-finite trajectory"
    elif defect > DYNAMICS_TOL:
        failure = f"dynamics defect {defect:.1e}"
    elif not (margin := verify.control_domain_margin(problem, u)) > 0:
        failure = f"control outside its model's domain by {-margin:.1e}"
    elif viol > COLLISION_TOL_M:
        failure = f"collision violation {viol:.1e} m"
    else:
        stat = verify.stationarity_residual(problem, x, u, relative=True)
        if not np.all(stat <= STATIONARITY_REL_TOL):
            failure = f"stationarity {stat.max():.1e}"
    feasibility, detail = failure_feasibility(problem, x, u) if failure else ("", "")
    # collision_gaps_m is h in metres (d_min - distance, positive = violated): slack = -h.
    min_slack = float(-np.max(gaps)) if np.size(gaps) else float("inf")
    so = getattr(r, "second_order", None)
    second_order_ok = None if so is None else bool(r.status != "saddle" and np.all(np.asarray(so) >= -SECOND_ORDER_TOL))
    return RunRecord(name, cars, seed, r.status, 1e3 * (r.solve_time_s + setup_s), int(r.iterations),
                     failure == "", failure, bool(np.size(gaps) and min_slack < ACTIVE_GAP_M), min_slack, family,
                     second_order_ok, cpu_ms, feasibility, detail)


def run(solvers: list[str], cars: list[int], instances, workers: int, time_limit_s: float,
        families: tuple[str, ...] = ("authors",), best_response_rounds: int = 0,
        max_iter: int | None = None, settings: tuple = (), repeats: int = 1,
        best_response_check: int = -1, steering_bound: float = math.inf) -> list[RunRecord]:
    """instances: a count (seeds 0..instances-1) or the seeds themselves. best_response_rounds > 0: RD3G starts
    from solver_cpp.best_response.best_response_guess (its time counts, within the time limit). time_limit_s <= 0: none.
    settings: RD3G setting overrides, (name, value) pairs. repeats: a solve faster than REPEAT_BELOW_MS (and than
    a tenth of its time limit) runs up to this many times and the fastest run's times are reported. best_response_check >= 0:
    every success is also checked by SLSQP best responses (best_response_gap) from it and that many perturbations;
    its time is not counted. steering_bound (rad): the families' variant with every car's steering bounded at it."""
    seeds = list(range(instances)) if isinstance(instances, int) else [int(s) for s in instances]
    jobs = [Job(s, n, seed, time_limit_s, f, best_response_rounds, max_iter, tuple(settings), repeats,
                best_response_check, steering_bound)
            for f in families for n in cars for s in solvers for seed in seeds]
    records: list[RunRecord] = []
    with tqdm(total=len(jobs), desc="bench merge", unit="solve") as bar:
        if workers <= 1:
            for job in jobs:
                records.append(one_run(job))
                bar.update()
        else:
            with ProcessPoolExecutor(max_workers=workers) as pool:
                for rec in pool.map(one_run, jobs, chunksize=4):
                    records.append(rec)
                    bar.update()
    return records


def summarize(records: list[RunRecord]) -> list[dict]:
    out = []
    keys = sorted({(r.solver, r.cars) for r in records}, key=lambda k: (SOLVERS.index(k[0]) if k[0] in SOLVERS else 9, k[1]))
    for s, n in keys:
        rs = [r for r in records if r.solver == s and r.cars == n]
        ok = [r for r in rs if r.success]
        t = np.array([r.solve_ms for r in ok])
        c = np.array([r.cpu_ms for r in ok])
        nan = None
        out.append({
            "solver": s, "cars": n, "instances": len(rs), "converged": len(ok),
            "mean_ms": float(t.mean()) if len(t) else nan, "median_ms": float(np.median(t)) if len(t) else nan,
            "p90_ms": float(np.percentile(t, 90)) if len(t) else nan,
            "median_cpu_ms": float(np.median(c)) if len(c) else nan,
            "infeasible": sum(r.feasibility == "infeasible" for r in rs),
            "feasibility_unknown": sum(r.feasibility == "unknown" for r in rs),
            "mean_iterations": float(np.mean([r.iterations for r in ok])) if ok else nan,
            "active_fraction": float(np.mean([r.active_collision for r in ok])) if ok else nan,
        })
    return out


def summarize_families(records: list[RunRecord]) -> list[dict]:
    """Per family, solver and size: success by the common test, the share of successes the second-order test
    confirms, statuses, median / p90 / max wall and CPU time (ms) and iterations over all runs (failures included:
    they cost time too), and the failures split by feasibility (proven infeasible, feasible, unknown)."""
    out = []
    for f, s, n in sorted({(r.family, r.solver, r.cars) for r in records}, key=lambda k: (k[0], k[1], k[2])):
        rs = [r for r in records if (r.family, r.solver, r.cars) == (f, s, n)]
        ok = [r for r in rs if r.success]
        t = np.array([r.solve_ms for r in rs])
        cpu = np.array([r.cpu_ms for r in rs])
        it = np.array([r.iterations for r in rs])
        so = [r.second_order_ok for r in ok if r.second_order_ok is not None]
        br = [r.best_response_gap for r in ok if r.best_response_gap is not None]
        statuses: dict[str, int] = {}
        for r in rs:
            statuses[r.status] = statuses.get(r.status, 0) + 1
        failed = [r for r in rs if not r.success]
        infeasible = sum(r.feasibility == "infeasible" for r in failed)
        solvable = len(rs) - infeasible  # instances not proven infeasible (unknown ones count as solvable)
        out.append({
            "family": f, "solver": s, "cars": n, "instances": len(rs), "solved": len(ok),
            "second_order_confirmed": int(sum(so)) if so else None,
            # successes no player improves on alone by more than verify.BEST_RESPONSE_TOL (None: check not run)
            "best_response_confirmed": (sum(bool(g <= verify.BEST_RESPONSE_TOL) for g in br)
                                        if br and len(br) == len(ok) else None),
            "best_response_worst_gap": float(np.nanmax(br)) if br and not np.all(np.isnan(br)) else None,
            "converged_but_rejected": sum(r.status == "converged" and r.second_order_ok is False for r in rs),
            "statuses": statuses,
            "median_ms": float(np.median(t)), "p90_ms": float(np.percentile(t, 90)), "max_ms": float(t.max()),
            "median_iterations": float(np.median(it)), "p90_iterations": float(np.percentile(it, 90)),
            "max_iterations": int(it.max()),
            "failures": [f"seed {r.seed}: {r.status}, {r.failure}" for r in rs if not r.success][:5],
            "median_cpu_ms": float(np.median(cpu)), "p90_cpu_ms": float(np.percentile(cpu, 90)),
            "max_cpu_ms": float(cpu.max()),
            "infeasible": infeasible,
            "failed_feasible": sum(r.feasibility == "feasible" for r in failed),
            "feasibility_unknown": sum(r.feasibility == "unknown" for r in failed),
            "solvable": solvable,
            "success_rate": len(ok) / len(rs),
            "success_rate_solvable": len(ok) / solvable if solvable else None,
            "failed_instances": [failure_row(r) for r in failed],
        })
    return out


def failure_row(r: RunRecord) -> dict:
    return {"family": r.family, "solver": r.solver, "cars": r.cars, "seed": r.seed, "status": r.status,
            "failure": r.failure, "feasibility": r.feasibility, "feasibility_detail": r.feasibility_detail,
            "iterations": r.iterations, "solve_ms": r.solve_ms, "cpu_ms": r.cpu_ms}


def budget_text(max_iter: int | None, time_limit_s: float) -> str:
    return (f"max_iter {'the solver default' if max_iter is None else max_iter}, "
            f"time limit {'none' if time_limit_s <= 0 else f'{time_limit_s:g} s'}")


def family_markdown(summary: list[dict], command: str, machine: str, seconds: float, best_response_rounds: int = 0,
                    budget: str = "", repeats: int = 1) -> str:
    """One solver: the detailed table and every failure. Several: the side-by-side table (family_comparison) and the
    failures counted per solver and feasibility verdict (each one is in the JSON's failed_instances).
    repeats: the runs per short solve (Job.repeats)."""
    solvers = solvers_in(summary)
    guess = (f" (initial guess: {best_response_rounds} rounds of iterated best response, time included)"
             if best_response_rounds else "")
    # Named in the heading unless they are the tuned group, so that each selection's block is told apart.
    families = list(dict.fromkeys(r["family"] for r in summary))
    named = "" if sorted(families) == sorted(TUNED_FAMILIES) else f" ({', '.join(families)})"
    lines = [
        ("## Game families: RD3G beyond the authors' merging benchmark" if len(solvers) < 2 else
         "## Game families: " + ", ".join(solvers) + " side by side") + named + guess,
        "",
        f"Command: `{command}` ({seconds:.0f} s). Machine: {machine}." + (f" Budget per solve: {budget}." if budget else ""),
        "Families: docs/merging.md, 'Other families'. solved = the common test of the three-solver table (dynamics, "
        f"controls inside their models' domains, collision violation <= {COLLISION_TOL_M:g} m, per-player stationarity <= {STATIONARITY_REL_TOL:g}), as a share "
        "of all instances and of the solvable ones (all but the proven infeasible); "
        "2nd order = share of the solved results whose every player passes the solver's second-order test"
        + ("" if not any(r.get("best_response_confirmed") is not None for r in summary) else
           f" (best response: solved results on which no player lowers its cost by more than "
           f"{verify.BEST_RESPONSE_TOL:g} of it by deviating alone, SLSQP from the result and seeded perturbations, "
           "bench/verify.py)") + "; "
        "'conv. rejected' = results reported converged at a point the test rejects (must be 0); "
        "failures: infeasible = proven infeasible, unknown = neither proven infeasible nor shown feasible "
        "(docs/benchmarks.md, 'Budgets, CPU time and infeasible instances'). Wall and CPU times and iterations over "
        "all instances, failures included; CPU = time.process_time of the worker around the solve (and any "
        "best-response guess)." + (f" A solve under {REPEAT_BELOW_MS:g} ms CPU (and under a tenth of its time limit) ran up to "
                                   f"{repeats} times (the same result each time) and its fastest run's times are shown."
                                   if repeats > 1 else ""),
    ]
    failed = [f for r in summary for f in r["failed_instances"]]
    if len(solvers) > 1:
        lines += family_comparison(summary)
        lines += ["", "Failures per solver (infeasible / feasible / unknown; each with its verdict in the JSON's "
                      "failed_instances):"]
        for s in solvers:
            fs = [f for f in failed if f["solver"] == s]
            lines.append(f"- {s}: {len(fs)} (" + " / ".join(str(sum(f['feasibility'] == v for f in fs))
                                                         for v in ("infeasible", "feasible", "unknown")) + ")")
        return "\n".join(lines)
    lines += [
        "",
        "| family | cars | solved (all / solvable) | 2nd order | conv. rejected | failures: infeasible / unknown | "
        "statuses | wall ms median / p90 / max | CPU ms median / p90 / max | iterations median / p90 / max |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in summary:
        so = "—" if r["second_order_confirmed"] is None or not r["solved"] else \
            f"{100 * r['second_order_confirmed'] / r['solved']:.0f}%"
        if r.get("best_response_confirmed") is not None:
            so += f"; best response {r['best_response_confirmed']}/{r['solved']}"
        st = ", ".join(f"{k} {v}" for k, v in sorted(r["statuses"].items()))
        solvable = "—" if r["success_rate_solvable"] is None else f"{100 * r['success_rate_solvable']:.0f}%"
        lines.append(f"| {r['family']} ({r['solver']}) | {r['cars']} | {r['solved']}/{r['instances']} "
                     f"({100 * r['solved'] / r['instances']:.0f}% / {solvable}) | {so} | {r['converged_but_rejected']} | "
                     f"{r['infeasible']} / {r['feasibility_unknown']} | {st} | "
                     f"{r['median_ms']:.1f} / {r['p90_ms']:.1f} / {r['max_ms']:.0f} | "
                     f"{r['median_cpu_ms']:.1f} / {r['p90_cpu_ms']:.1f} / {r['max_cpu_ms']:.0f} | "
                     f"{r['median_iterations']:.0f} / {r['p90_iterations']:.0f} / {r['max_iterations']} |")
    lines += ["", f"Failures ({len(failed)}): " + ("none" if not failed else "")]
    lines += [f"- {f['family']} {f['cars']} cars seed {f['seed']} ({f['solver']}): {f['status']}, {f['failure']}; "
              f"{f['feasibility']} ({f['feasibility_detail']})" for f in failed]
    return "\n".join(lines)


P90_OVER_MEDIAN_GOAL = 10.0  # issue #31's speed goal: RD3G's p90 CPU time at most this many times its median


def speed_goal(records: list[RunRecord], limit_s: float) -> list[dict]:
    """Issue #31's speed goal per family and size: RD3G's median CPU time at most the faster baseline's (the lower
    median of iLQGames and ALGames), every failure counted as the time limit (limit_s) whatever it cost, and RD3G's
    p90 at most P90_OVER_MEDIAN_GOAL times its median (the same counting)."""
    limit_ms = 1e3 * limit_s

    def counted(rs):
        return np.array([r.cpu_ms if r.success else limit_ms for r in rs])

    rows = []
    for f, n in sorted({(r.family, r.cars) for r in records if r.solver == "rd3g"}):
        cell = {s: counted([r for r in records if (r.family, r.cars, r.solver) == (f, n, s)]) for s in SOLVERS}
        ours = cell["rd3g"]
        baselines = {s: float(np.median(c)) for s, c in cell.items() if s != "rd3g" and c.size}
        faster = min(baselines, key=baselines.get) if baselines else None
        median, p90 = float(np.median(ours)), float(np.percentile(ours, 90))
        rows.append({"family": f, "cars": n, "instances": int(ours.size), "median_cpu_ms": median,
                     "p90_cpu_ms": p90, "baseline_median_cpu_ms": baselines, "faster_baseline": faster,
                     "median_goal_met": None if faster is None else median <= baselines[faster],
                     "p90_goal_met": p90 <= P90_OVER_MEDIAN_GOAL * median})
    return rows


def speed_goal_markdown(rows: list[dict], limit_s: float) -> list[str]:
    def verdict(ok):
        return "—" if ok is None else "yes" if ok else "**no**"

    lines = ["", f"Speed goal (issue #31): CPU ms per solve, every failure counted as the time limit ({limit_s:g} s); "
                 f"RD3G's median at most the faster baseline's, its p90 at most {P90_OVER_MEDIAN_GOAL:g}x its median.",
             "", "| family | cars | rd3g median / p90 | ilqgames median | algames median | median <= faster baseline "
                 f"| p90 <= {P90_OVER_MEDIAN_GOAL:g}x median |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        base = [f"{r['baseline_median_cpu_ms'][s]:.1f}" if s in r["baseline_median_cpu_ms"] else "—"
                for s in ("ilqgames", "algames")]
        lines.append(f"| {r['family']} | {r['cars']} | {r['median_cpu_ms']:.1f} / {r['p90_cpu_ms']:.1f} | "
                     f"{base[0]} | {base[1]} | {verdict(r['median_goal_met'])} | {verdict(r['p90_goal_met'])} |")
    met = sum(bool(r["median_goal_met"]) and r["p90_goal_met"] for r in rows)
    lines += ["", f"Both goals met in {met} of {len(rows)} cells."]
    return lines


def solvers_in(summary: list[dict]) -> list[str]:
    """The solvers a summary has rows for, in SOLVERS order."""
    return [s for s in SOLVERS if any(r["solver"] == s for r in summary)]


def family_comparison(summary: list[dict]) -> list[str]:
    """With more than one solver: per family and size, each solver's solved count and median / p90 CPU ms side by
    side; nothing for one solver."""
    solvers = solvers_in(summary)
    if len(solvers) < 2:
        return []
    by = {(r["family"], r["cars"], r["solver"]): r for r in summary}
    lines = ["", "Side by side (solved; CPU ms median / p90, failures included):", "",
             "| family | cars | " + " | ".join(solvers) + " |", "|---|---|" + "---|" * len(solvers)]
    for f, n in sorted({(r["family"], r["cars"]) for r in summary}):
        cells = []
        for s in solvers:
            r = by.get((f, n, s))
            cells.append("—" if r is None else
                         f"{r['solved']}/{r['instances']}; {r['median_cpu_ms']:.1f} / {r['p90_cpu_ms']:.1f}")
        lines.append(f"| {f} | {n} | " + " | ".join(cells) + " |")
    return lines


def _fmt(v, spec=".1f"):
    return "—" if v is None else format(v, spec)


def markdown(summary: list[dict], command: str, machine: str, seconds: float, figures: list[str]) -> str:
    by = {(r["solver"], r["cars"]): r for r in summary}
    solvers = [s for s in SOLVERS if any(k[0] == s for k in by)]
    cars = sorted({k[1] for k in by})
    head = "| cars | " + " | ".join(f"{s} ours: median / mean ms (success) | {s} paper mean ms" for s in solvers) + " |"
    lines = [
        "## Merging benchmark: RD3G vs iLQGames vs ALGames (paper Table I)",
        "",
        f"Command: `{command}` ({seconds:.0f} s). Machine: {machine}.",
        "All solvers in C++ sharing the models and derivatives, run on the same instances with the same time limit.",
        f"Success = the common test on the returned trajectories: dynamics defect <= {DYNAMICS_TOL:g}, every control inside "
        f"its model's domain (bench/verify.py), collision violation <= "
        f"{COLLISION_TOL_M:g} m, every player's stationarity residual (least-squares multipliers, bench/verify.py) <= "
        f"{STATIONARITY_REL_TOL:g} of the cost-gradient scale. Times over successful runs. 'active' = share of successful runs "
        f"with a collision constraint within {ACTIVE_GAP_M:g} m of active.",
        "",
        head,
        "|---|" + "---|---|" * len(solvers),
    ]
    for n in cars:
        cells = []
        for s in solvers:
            r = by.get((s, n))
            paper = PAPER_MS.get(s, {}).get(n)
            if r is None:
                cells += ["", ""]
                continue
            rate = 100 * r["converged"] / r["instances"]
            cells.append(f"{_fmt(r['median_ms'])} / {_fmt(r['mean_ms'])} ({rate:.0f}%, active {_fmt(r['active_fraction'], '.0%') if r['active_fraction'] is not None else '—'})")
            cells.append("N/C" if s == "ilqgames" and n == 8 else _fmt(paper, "d") if paper else "")
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    lines += [""] + [f"![{f}]({f})" for f in figures]
    return "\n".join(lines)


def plot_times(summary: list[dict], path: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for s in SOLVERS:
        rows = [r for r in summary if r["solver"] == s and r["median_ms"] is not None]
        if rows:
            ax.plot([r["cars"] for r in rows], [r["median_ms"] for r in rows], "o-", label=f"{s} (ours, median)")
        paper = PAPER_MS[s]
        ax.plot([n for n, v in paper.items() if v], [v for v in paper.values() if v], "x--", alpha=0.6, label=f"{s} (paper, mean)")
    ax.set_yscale("log")
    ax.set_xlabel("cars")
    ax.set_ylabel("solve time (ms)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    atomic_write_with(path, lambda tmp: fig.savefig(tmp, dpi=120, format=Path(path).suffix.lstrip(".") or "png"))
    plt.close(fig)
    return path


def plot_merge(cars: int, seed: int, path: str) -> str:
    """Lanes, car footprints at several instants and the trajectories of one RD3G solution."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle
    from matplotlib.transforms import Affine2D

    problem = merging_problem(cars, seed)
    r = solve(problem)
    n_main, _ = lane_counts(cars)
    x = r.x
    fig, ax = plt.subplots(figsize=(10, 2.8))
    lo, hi = x[:, :, 0].min() - 3, x[:, :, 0].max() + 3
    for y in (MAIN_LANE_Y, MERGE_LANE_Y):
        ax.axhline(y, color="0.7", ls="--", lw=0.8)
    for y in (MAIN_LANE_Y + 1.1, 0.0, MERGE_LANE_Y - 1.1):
        ax.axhline(y, color="0.3", lw=1.0 if y else 0.6)
    colors = plt.cm.tab10(np.arange(cars) % 10)
    instants = np.linspace(0, problem.horizon, 5).astype(int)
    for i in range(cars):
        ax.plot(x[i, :, 0], x[i, :, 1], "-", color=colors[i], lw=1.2,
                label=f"car {i} ({'main' if i < n_main else 'merging'})")
        for a, k in enumerate(instants):
            px, py, _, th = x[i, k]
            rect = Rectangle((-1.0, -0.45), 2.0, 0.9, color=colors[i], alpha=0.15 + 0.7 * a / len(instants))
            rect.set_transform(Affine2D().rotate(th).translate(px, py) + ax.transData)
            ax.add_patch(rect)
    ax.set_xlim(lo, hi)
    ax.set_ylim(-2.6, 2.6)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{cars}-car merge, seed {seed}: {r.status}, {1e3 * r.solve_time_s:.0f} ms "
                 f"(footprints at t = {', '.join(f'{k * problem.dt:.1f}' for k in instants)} s)", fontsize=9)
    ax.legend(fontsize=6, ncol=min(cars, 4), loc="upper left")
    fig.tight_layout()
    atomic_write_with(path, lambda tmp: fig.savefig(tmp, dpi=120, format=Path(path).suffix.lstrip(".") or "png"))
    plt.close(fig)
    return path


def records_json(summary: list[dict]) -> dict:
    return {"results": summary}


__all__ = ["run", "summarize", "summarize_families", "family_markdown", "speed_goal", "speed_goal_markdown", "failure_feasibility", "Job", "markdown", "plot_times", "plot_merge", "RunRecord", "asdict"]
