"""Markdown report, residual plots and the JSON summary of an identification run."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

import fileio

from sysid.diagnose import (EFFECT_NAMES, ErrorSummary, Fit, SysidResult, block_length, heldout_runs,
                             per_run_summaries)
from sysid.run_level import RunLevelParam

# Per effect: (label of the explaining variable, label of the residual it drives).
EXPLAINING_VARIABLES = {
    "actuation_delay": ("mean speed x steering change over the window v·(δ_end − δ_start) [rad·m/s]",
                        "heading error at horizon [rad]"),
    "steering_offset": ("mean speed over the window [m/s]", "heading error at horizon [rad]"),
    "steering_gain": ("mean speed x steering command over the window [rad·m/s]", "heading error at horizon [rad]"),
    "tire_slip": ("mean lateral acceleration v·r over the window [m/s²]", "lateral position error at horizon [m]"),
    "longitudinal_drag": ("mean v·|v| over the window [m²/s²]", "speed error at horizon [m/s]"),
    "steering_backlash": ("mean speed x steering reversal over the window v·(δ_end − 2δ_mid + δ_start) [rad·m/s]",
                          "heading error at horizon [rad]"),
    "steering_asymmetry": ("mean speed x |steering command| over the window [rad·m/s]",
                           "heading error at horizon [rad]"),
    "motor_drift": ("time since the run's start [s]", "speed error at horizon [m/s]"),
    "throttle_map": ("mean |throttle| over the window", "speed error at horizon [m/s]"),
    "speed_map": ("mean speed set-point over the window [m/s]", "speed error at horizon [m/s]"),
    "speed_response": ("set-point minus speed at the window start [m/s]", "speed error at horizon [m/s]"),
    "other": ("mean speed over the window [m/s]", "heading error at horizon [rad]"),
}


def explaining_variable(result: SysidResult, effect: str) -> np.ndarray:
    traj, starts, h = result.traj, result.split.heldout, result.horizon_steps
    window = starts[:, None] + np.arange(h + 1)[None, :]
    v = traj.speed[window]
    if effect == "actuation_delay":
        # A dead time d leaves a heading error of about -(v/L) d (delta_end - delta_start) over the window.
        return np.mean(v, axis=1) * (traj.steering[starts + h - 1] - traj.steering[starts])
    if effect == "steering_gain":
        return np.mean(v * traj.steering[window], axis=1)
    if effect == "steering_backlash":
        mid = starts + h // 2
        return np.mean(v, axis=1) * (traj.steering[starts + h - 1] - 2 * traj.steering[mid] + traj.steering[starts])
    if effect == "steering_asymmetry":
        return np.mean(v * np.abs(traj.steering[window]), axis=1)
    if effect == "motor_drift":
        return traj.elapsed[starts]
    if effect == "tire_slip":
        return np.mean(v * traj.yaw_rate[window], axis=1)
    if effect == "speed_map":
        return np.mean(traj.throttle[window], axis=1)
    if effect == "throttle_map":
        return np.mean(np.abs(traj.throttle[window]), axis=1)
    if effect == "speed_response":
        return traj.throttle[starts] - traj.speed[starts]
    if effect == "longitudinal_drag":
        return np.mean(v * np.abs(v), axis=1)
    return np.mean(v, axis=1)


def residual_for(fit: Fit, effect: str) -> np.ndarray:
    e = fit.heldout_errors
    if effect == "tire_slip":
        return e.lateral[:, -1]
    if effect in ("longitudinal_drag", "motor_drift", "throttle_map", "speed_map", "speed_response"):
        return e.speed[:, -1]
    return e.heading[:, -1]


def plot_residual(result: SysidResult, effect: str, before: Fit, after: Fit, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = explaining_variable(result, effect)
    xlabel, ylabel = EXPLAINING_VARIABLES[effect]
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=110)
    edges = np.quantile(x, np.linspace(0, 1, 13))
    centres = 0.5 * (edges[1:] + edges[:-1])
    which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    for fit, label, colour in ((before, "before", "tab:red"), (after, "after", "tab:blue")):
        y = residual_for(fit, effect)
        ax.scatter(x, y, s=3, alpha=0.15, color=colour, linewidths=0)
        med = np.array([np.median(y[which == i]) if np.any(which == i) else np.nan for i in range(centres.size)])
        ax.plot(centres, med, "o-", color=colour, label=f"{label} (binned median)")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(f"held-out residual vs explaining variable: {effect}")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fileio.atomic_write_with(path, lambda tmp: fig.savefig(tmp, format="png"))
    plt.close(fig)
    return path


def make_plots(result: SysidResult, figure_dir: Path, stem: str) -> list[tuple[str, Path]]:
    """One PNG per claimed effect (before = model without it, after = with it); the top
    candidate's plot when nothing is claimed."""
    figure_dir.mkdir(parents=True, exist_ok=True)
    plots = []
    if result.selected:
        for sel, (before, after) in zip(result.selected, result.effect_steps):
            path = figure_dir / f"{stem}_{sel.effect}.png"
            plots.append((sel.effect, plot_residual(result, sel.effect, before, after, path)))
    else:
        top = result.candidates[0].effect
        path = figure_dir / f"{stem}_{top}.png"
        plots.append((top, plot_residual(result, top, result.reference, result.final, path)))
    return plots


def result_json(result: SysidResult, car_params_out: str) -> dict[str, Any]:
    """The JSON summary (keys documented in docs/sysid.md, "Outputs")."""
    return {
        "significant": result.significant,
        "effects": [
            {
                "effect": e.effect,
                "params": {k: float(v) for k, v in e.params.items()},
                "params_std": {k: float(v) for k, v in e.params_std.items()},
                "heldout_error_reduction": float(e.reduction_vs_nominal),
                "heldout_error_reduction_vs_without": float(e.heldout_error_reduction),
            }
            for e in result.selected
        ],
        "before": result.planner.heldout.json_dict(),
        "after": result.final.heldout.json_dict(),
        "dynamic_nominal": result.dynamic_nominal.heldout.json_dict(),
        "planner_new_corrections": result.planner_after.heldout.json_dict(),
        "heldout_error_reduction": float(result.heldout_error_reduction),
        "unnamed_effect_remains": result.unnamed_effect_remains,
        "dropped_after_other": list(result.dropped_after_other),
        "car_params_out": car_params_out,
        "geometry_diagnosis": result.geometry_diagnosis,
        "not_identifiable": [{"effect": n.effect, "params": list(n.params), "reasons": list(n.reasons)}
                             for n in result.not_identifiable],
        "run_agreement": [
            {"effect": a.effect, "param": a.param, "verdict": a.agreement.verdict,
             "runs": [{"run": r + 1, "source": result.traj.runs[r].source, "value": v, "std": e}
                      for r, v, e in zip(a.runs, a.values, a.stds)],
             "excluded_runs": [result.traj.runs[r].source for r in a.excluded_runs],
             "pooled": a.agreement.pooled.mean, "pooled_std": a.agreement.pooled.std, "tau": a.agreement.pooled.tau,
             "q": a.agreement.pooled.q, "p_value": a.agreement.pooled.p_value}
            for a in result.run_agreement
        ],
        "claim_stability": [
            {"effect": k.effect, "dropped_run": k.dropped_run + 1, "source": result.traj.runs[k.dropped_run].source,
             "params": {p: float(v) for p, v in k.values.items()}, "significant": k.significant,
             "heldout_error_reduction_vs_without": float(k.verdict.heldout_error_reduction),
             "heading_reduction": float(k.verdict.heading_reduction), "speed_reduction": float(k.verdict.speed_reduction),
             "confidence": float(k.verdict.confidence),
             "on_run": None if k.on_run is None else {
                 "significant": k.on_run.significant,
                 "heldout_error_reduction_vs_without": float(k.on_run.heldout_error_reduction),
                 "heading_reduction": float(k.on_run.heading_reduction),
                 "speed_reduction": float(k.on_run.speed_reduction), "confidence": float(k.on_run.confidence)}}
            for k in result.claim_stability
        ],
        "run_level": [run_level_json(result, p) for p in result.run_level],
        "other_cross_run": [
            {"run": k.run + 1, "source": result.traj.runs[k.run].source, "params": dict(k.params),
             "significant": k.significant, "heldout_error_reduction_vs_without": float(k.verdict.heldout_error_reduction),
             "heading_reduction": float(k.verdict.heading_reduction), "speed_reduction": float(k.verdict.speed_reduction),
             "confidence": float(k.verdict.confidence)}
            for k in result.other_cross_run
        ],
        "heldout_runs": [
            {"run": i + 1, "source": result.traj.runs[i].source, "windows": n,
             "dynamic_nominal": nominal.json_dict(), "planner": planner.json_dict(), "after": after.json_dict()}
            for i, n, nominal, planner, after in per_run_summaries(result)
        ],
    }


def run_level_json(result: SysidResult, p: RunLevelParam) -> dict[str, Any]:
    """A run-level parameter (docs/sysid.md, "Run-level parameters")."""
    src = lambda r: result.traj.runs[r].source  # noqa: E731
    opt = lambda e: None if e is None else e.json_dict()  # noqa: E731
    pop, v = p.population, p.verdict
    return {
        "effect": p.effect, "param": p.param, "nominal": p.nominal,
        "runs": [{"run": r.run + 1, "source": src(r.run), "value": r.value, "std": r.std, "windows": r.windows}
                 for r in p.runs],
        "not_excited": [{"run": r + 1, "source": src(r), "reason": why} for r, why in p.not_excited],
        "population": pop.value, "population_std": pop.std, "log_spread": pop.log_pool.tau,
        "spread_factor": pop.spread_factor, "run_std": pop.run_std, "q": pop.log_pool.q,
        "p_value": pop.log_pool.p_value,
        "keep_test": {"significant": v.significant, "heldout_error_reduction_vs_without": v.heldout_error_reduction,
                      "heading_reduction": v.heading_reduction, "speed_reduction": v.speed_reduction,
                      "confidence": v.confidence},
        "written": p.written,
        "heldout_runs": [
            {"run": h.run + 1, "source": src(h.run), "windows": h.windows, "shared": h.shared.json_dict(),
             "population": h.population.json_dict(),
             "calibration": {"block_s": h.calibration.block_s, "windows": h.calibration.windows,
                             "value": h.calibration.value, "std": h.calibration.std, "reason": h.calibration.reason,
                             "shared": opt(h.calibration.shared), "population": opt(h.calibration.population),
                             "calibrated": opt(h.calibration.calibrated)}}
            for h in p.heldout
        ],
    }


def disagreement_notes(result: SysidResult) -> list[str]:
    """One sentence per parameter on which runs disagree: which runs, their estimates and the others'."""
    notes = []
    for a in result.run_agreement:
        odd = a.runs if a.agreement.disagree else a.excluded_runs
        if not odd:
            continue
        name = lambda r: Path(result.traj.runs[r].source).name  # noqa: E731
        est = dict(zip(a.runs, zip(a.values, a.stds)))
        odd_text = ", ".join(f"{name(r)} {est[r][0]:.3g} ± {est[r][1]:.2g}" for r in odd)
        if a.agreement.disagree:
            notes.append(f"Runs disagree on {a.effect} (`{a.param}`): {odd_text}; no majority agrees, not fitted or "
                         "claimed.")
        else:
            rest = ", ".join(name(r) for r in a.agreeing_runs)
            notes.append(f"Runs disagree on {a.effect} (`{a.param}`): {odd_text} vs {rest} "
                         f"{a.agreement.pooled.mean:.3g} ± {a.agreement.pooled.std:.2g}; fitted on {rest} only.")
    return notes


def instability_notes(result: SysidResult) -> list[str]:
    """One sentence per effect not claimed because it needs one particular training run."""
    notes = []
    for effect in dict.fromkeys(k.effect for k in result.claim_stability if not k.significant):
        failing = [k for k in result.claim_stability if k.effect == effect and not k.significant]

        def where(k) -> str:
            v, on = (k.verdict, "held-out data") if not k.verdict.significant else (k.on_run, "run itself")
            return (f"{Path(result.traj.runs[k.dropped_run].source).name} ({on}: {100 * v.heldout_error_reduction:.0f} % "
                    f"position, {100 * v.heading_reduction:+.0f} % heading, {100 * v.speed_reduction:+.0f} % speed)")

        notes.append(f"{effect} is not stable across runs: without {', '.join(where(k) for k in failing)} it fails the "
                     "keep test; not claimed.")
    return notes


def other_cross_run_notes(result: SysidResult) -> list[str]:
    """One sentence when `other` was not claimed because it does not predict the training runs it was not fitted on."""
    failing = [k for k in result.other_cross_run if not k.significant]
    if not failing:
        return []
    runs = ", ".join(f"{Path(result.traj.runs[k.run].source).name} ({100 * k.verdict.heldout_error_reduction:.0f} % "
                     f"position, {100 * k.verdict.heading_reduction:+.0f} % heading, "
                     f"{100 * k.verdict.speed_reduction:+.0f} % speed)" for k in failing)
    return [f"other does not hold across runs: fitted without {runs} it fails the keep test on that run; not claimed."]


def run_level_notes(result: SysidResult) -> list[str]:
    """One sentence per run-level parameter: per-run values, population, and whether it is written."""
    notes = []
    for p in result.run_level:
        per = ", ".join(f"{Path(result.traj.runs[r.run].source).name} {r.value:.3g}" for r in p.runs)
        notes.append(f"{p.effect} is run-level (`{p.param}` per run: {per}); population {p.population.value:.3g} ± "
                     f"{p.population.std:.2g}, spread between runs x{p.population.spread_factor:.2f}; "
                     + ("written (passes the keep test held out)." if p.written else
                        "not written (fails the keep test held out)."))
    return notes


def write_json(result: SysidResult, path: Path, car_params_out: str) -> Path:
    fileio.atomic_write_text(path, json.dumps(result_json(result, car_params_out), indent=2) + "\n", stream=True)
    return path


def run_level_lines(result: SysidResult, p: RunLevelParam) -> list[str]:
    """The report's section on a run-level parameter."""
    name = lambda r: Path(result.traj.runs[r].source).name  # noqa: E731
    pop, v = p.population, p.verdict
    per = ", ".join(f"{name(r.run)} {r.value:.3g} ± {r.std:.2g}" for r in p.runs)
    lines = ["", f"## Run-level parameter: {p.effect} (`{p.param}`)", "",
             "Fitted on each training run on top of the shared model; the population is the random-effects pool of "
             "the runs' values on the log scale, its ± includes the spread between runs (docs/sysid.md, \"Run-level "
             "parameters\").", "",
             f"* Per run: {per}" + "".join(f"; {name(r)}: not fitted ({why})" for r, why in p.not_excited) + ".",
             f"* Population {pop.value:.3g} ± {pop.std:.2g}; spread between runs: a factor {pop.spread_factor:.2f} "
             f"(a new run: {pop.value:.3g} ± {pop.run_std:.2g}); Q p-value {pop.log_pool.p_value:.2g}.",
             f"* Held out, the population value against the car file's {p.nominal:g}: "
             f"{100 * v.heldout_error_reduction:+.1f} % position, {100 * v.heading_reduction:+.1f} % heading, "
             f"{100 * v.speed_reduction:+.1f} % speed (confidence {v.confidence:.2f}): "
             + ("passes the keep test, written to the car file." if p.written else
                "fails the keep test, nothing written (the car file keeps its value)."),
             "", "Held-out runs, horizon RMSE position cm / heading rad / speed m/s. All windows: shared model → "
             "population value. After the run's own first block: shared → population → calibrated on that block.", "",
             "| run | windows | shared → population | after block: windows | shared → population → calibrated | "
             "calibrated value |", "|---|---|---|---|---|---|"]
    fmt = lambda e: (f"{100 * e.horizon_pos_rmse_m:.1f} / {e.horizon_heading_rmse_rad:.3f} / "  # noqa: E731
                     f"{e.horizon_speed_rmse_mps:.3f}")
    for h in p.heldout:
        c = h.calibration
        cal = (f"{fmt(c.shared)} → {fmt(c.population)} → {fmt(c.calibrated)} | {c.value:.3g} ± {c.std:.2g}"
               if c.value is not None else f"— | not calibrated: {c.reason}")
        lines.append(f"| {name(h.run)} | {h.windows} | {fmt(h.shared)} → {fmt(h.population)} | first "
                     f"{c.block_s:g} s: {c.windows} | {cal} |")
    return lines


def _row(name: str, s: ErrorSummary) -> str:
    return (f"| {name} | {100 * s.one_step_pos_rmse_m:.2f} | {100 * s.one_step_pos_p95_m:.2f} | "
            f"{100 * s.horizon_pos_rmse_m:.1f} | {100 * s.horizon_pos_p50_m:.1f} | {100 * s.horizon_pos_p90_m:.1f} | "
            f"{100 * s.horizon_pos_p95_m:.1f} | {s.horizon_heading_rmse_rad:.3f} | {s.horizon_speed_rmse_mps:.3f} |")


def _fmt_params(params: dict[str, float], std: dict[str, float]) -> str:
    if not params:
        return "—"
    return ", ".join(f"`{k}` = {v:.4g} ± {std.get(k, float('nan')):.2g}" for k, v in params.items())


def markdown_report(result: SysidResult, log_path: str, car_in: str, car_out: str, json_path: str | None,
                    plots: list[tuple[str, Path]], report_dir: Path, command: str | None = None,
                    log_note: str | None = None) -> str:
    s, traj = result.settings, result.traj
    lines = ["# Model identification report", ""]
    if command:
        lines += [f"Command: `{command}`", ""]
    held = heldout_runs(traj, s)
    split_note = (f"run{'s' if len(held) > 1 else ''} {', '.join(str(i + 1) for i in held)} held out whole (cross-run validation)" if held else
                  f"time blocks of {block_length(traj, s):.1f} s, every {s.heldout_every}rd held out")
    lines += [
        f"* Log{'s' if traj.n_runs > 1 else ''}: `{log_path}` — {traj.n_raw_rows} rows, {traj.n_duplicates_merged} "
        f"rows merged (equal time stamps or frames), {traj.n_gaps} gap(s); {traj.n} samples on a "
        f"{traj.dt * 1000:.2f} ms grid ({sum(r.duration_s for r in traj.runs):.1f} s)"
        + (f"; {log_note}." if log_note else "."),
        f"* Car parameters in: `{car_in}`; out: `{car_out}`" + (f"; JSON: `{json_path}`." if json_path else "."),
        f"* Horizon {result.horizon_steps} steps ({result.horizon_steps * traj.dt:.2f} s); "
        f"{result.split.train.size} training and {result.split.heldout.size} held-out windows ({split_note}).",
        f"* Estimated measurement noise: position {traj.position_noise_m * 1000:.1f} mm, heading "
        f"{traj.heading_noise_rad:.4f} rad.",
    ]
    if result.numeric_warnings:
        lines.append(f"* {result.numeric_warnings} numpy warning(s) (overflow or invalid values in trial predictions of the "
                     "fits; such trials cost the fit a large residual and are rejected).")
    lines.append("")
    if traj.n_runs > 1 or traj.runs[0].n_missing_frames:
        lines += ["| run | file | rows | merged | missing frames | gaps | samples | duration | role |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for i, r in enumerate(traj.runs):
            lines.append(f"| {i + 1} | `{r.source}` | {r.n_raw_rows} | {r.n_duplicates_merged} | {r.n_missing_frames} | "
                         f"{r.n_gaps} | {r.n_samples} | {r.duration_s:.1f} s | "
                         f"{'held out' if i in held else ('fit' if held else 'fit + held-out blocks')} |")
        lines.append("")
    lines += ["## Verdict", ""]
    if result.selected:
        names = ", ".join(f"**{e.effect}**" for e in result.selected)
        lines.append(f"Significant effect(s), best first: {names}. Held-out horizon position RMSE "
                     f"{100 * result.dynamic_nominal.heldout.horizon_pos_rmse_m:.1f} cm (nominal dynamic model) → "
                     f"{100 * result.final.heldout.horizon_pos_rmse_m:.1f} cm (final model): "
                     f"{100 * result.heldout_error_reduction:.0f} % reduction.")
        if result.unnamed_effect_remains:
            lines += ["", "**An effect the tool cannot name remains.** The named candidates do not explain all of "
                      "the error; the sparse terms of `other` (below) carry the rest. They are written to the car "
                      "file's `[other_terms]` table (applied by the simulator and by this tool's models; the "
                      "planner's kinematic model does not apply them, docs/sysid.md)."]
        if result.dropped_after_other:
            lines += ["", "Dropped once `other` was in the model (no longer significant on held-out data): "
                      + ", ".join(f"`{e}`" for e in result.dropped_after_other) + "."]
    else:
        lines.append("**No significant effect**: no candidate reduces the held-out horizon position error by at "
                     f"least {100 * s.min_reduction:.0f} % with {100 * s.confidence:.0f} % bootstrap confidence; "
                     "the corrections are left unchanged.")
    lines.append("")
    if result.geometry_diagnosis:
        lines += [f"**Geometry / steering scale.** {result.geometry_diagnosis['note']}.", ""]
    st = result.structure
    if result.reference_is_dynamic:
        lines += [
            "**Model structure.** "
            + ("Forward selection was run on top of the planner's kinematic model and on top of the car's own "
               "dynamic model (same parameters, Pacejka tyres); the dynamic family predicts the training windows "
               "better after the effects are fitted, so effects are reported against it. "
               if result.families_compared else
               "The car's own dynamic model (same parameters, Pacejka tyres) predicts the training windows "
               "significantly better than the planner's kinematic model already at the current parameters, so "
               "effects are fitted and reported against it. ")
            + f"At the current parameters the dynamic model changes the held-out horizon position RMSE by "
            f"{-100 * st.heldout_error_reduction:+.0f} %. That part is a limit of the kinematic model (the car "
            "slides as its nominal tyre parameters say), not a parameter deviation: a planner that keeps the "
            "kinematic model keeps it (row \"planner, new corrections\" below).",
            "",
        ]
        if result.switched_after:
            lines += [f"(The switch to the dynamic model was made during forward selection, after "
                      f"{', '.join(result.switched_after)}; that effect's reduction is against the kinematic model.)",
                      ""]
    else:
        lines += ["The planner's kinematic model is the reference: with the effects fitted it predicts the training "
                  "windows at least as well as the dynamic model (at the current parameters alone the dynamic "
                  f"model changes the held-out error by {-100 * st.heldout_error_reduction:+.0f} %).", ""]

    lines += [
        "## Prediction error on held-out data",
        "",
        "Position in cm (one step and at the end of the horizon), heading in rad, speed in m/s.",
        "",
        "| model | 1-step RMSE | 1-step p95 | horizon RMSE | p50 | p90 | p95 | heading RMSE | speed RMSE |",
        "|---|---|---|---|---|---|---|---|---|",
        _row("before: planner's model, current corrections", result.planner.heldout),
        _row("nominal dynamic model, current corrections (headline baseline)", result.dynamic_nominal.heldout),
        _row("after: reference model + identified effects", result.final.heldout),
        _row("planner, new corrections", result.planner_after.heldout),
        "",
    ]
    if traj.n_runs > 1:
        lines += ["Per held-out run (horizon RMSE: position cm, heading rad, speed m/s; nominal dynamic → after):", "",
                  "| run | windows | position | heading | speed |", "|---|---|---|---|---|"]
        for i, n, nominal, _, after in per_run_summaries(result):
            lines.append(f"| {i + 1} `{traj.runs[i].source}` | {n} | {100 * nominal.horizon_pos_rmse_m:.1f} → "
                         f"{100 * after.horizon_pos_rmse_m:.1f} | {nominal.horizon_heading_rmse_rad:.3f} → "
                         f"{after.horizon_heading_rmse_rad:.3f} | {nominal.horizon_speed_rmse_mps:.3f} → "
                         f"{after.horizon_speed_rmse_mps:.3f} |")
        lines.append("")
    lines += [
        "## Candidates",
        "",
        "Each candidate fitted alone on the training blocks on top of the reference model; reduction = "
        "1 − RMSE_after / RMSE_before of the held-out horizon position error (heading / speed: the same for their "
        "errors; a claim may not make either worse by more than "
        f"{100 * s.max_worsening:.0f} %); confidence = block-bootstrap "
        "probability that the held-out mean squared error went down. Standard deviations are cluster-robust "
        "(sandwich) estimates from the least-squares Jacobian.",
        "",
        "| effect | fitted parameters | held-out reduction | heading / speed | confidence | significant |",
        "|---|---|---|---|---|---|",
    ]
    for c in result.candidates:
        lines.append(f"| {c.effect} | {_fmt_params(c.params, c.params_std)} | {100 * c.heldout_error_reduction:+.1f} % "
                     f"| {100 * c.heading_reduction:+.1f} % / {100 * c.speed_reduction:+.1f} % "
                     f"| {c.confidence:.2f} | {'yes' if c.significant else 'no'} |")
    if result.not_identifiable:
        lines += ["", "## Not identifiable from these logs", "",
                  "Not fitted, not claimed, nothing written to the car file: the training windows do not excite them "
                  "(docs/sysid.md, \"Excitation tests\").", "", "| effect | parameter | reason |", "|---|---|---|"]
        for n in result.not_identifiable:
            for p, why in zip(n.params, n.reasons):
                lines.append(f"| {n.effect} | `{p}` | {why} |")
    if result.run_agreement:
        lines += ["", "## Agreement between runs", "",
                  "Each candidate fitted alone on each training run; per parameter the runs' estimates are pooled "
                  "(random effects) and tested for agreement (docs/sysid.md, \"Agreement between runs\"). Runs that "
                  "disagree are left out of that effect's fits; where no majority agrees, the parameter is not "
                  "fitted or claimed.", "",
                  "| effect | parameter | per run (value ± std) | pooled ± std (spread tau) | Q p-value | verdict |",
                  "|---|---|---|---|---|---|"]
        for a in result.run_agreement:
            per = ", ".join(f"{r + 1}: {v:.4g} ± {e:.2g}" for r, v, e in zip(a.runs, a.values, a.stds))
            verdict = a.agreement.verdict
            if a.excluded_runs:
                verdict += ": " + ", ".join(f"run {r + 1}" for r in a.excluded_runs) + " excluded"
            lines.append(f"| {a.effect} | `{a.param}` | {per} | {a.agreement.pooled.mean:.4g} ± "
                         f"{a.agreement.pooled.std:.2g} ({a.agreement.pooled.tau:.2g}) | {a.agreement.pooled.p_value:.2g} "
                         f"| {verdict} |")
        for note in disagreement_notes(result):
            lines += ["", note]
    if result.claim_stability:
        lines += ["", "## Stable under leaving out a run", "",
                  "Each claim refitted with each training run left out and judged by the keep test on the same "
                  "held-out data and on the left-out run's own windows (docs/sysid.md, \"Stable under leaving out a "
                  "run\"); the reported ± includes the jackknife's standard deviation of these values.", "",
                  "| effect | run left out | parameters | held-out position / heading / speed vs without it | "
                  "on the run left out | keep |",
                  "|---|---|---|---|---|---|"]

        def changes(v) -> str:
            return (f"{100 * v.heldout_error_reduction:.1f} / {100 * v.heading_reduction:+.1f} / "
                    f"{100 * v.speed_reduction:+.1f} %")

        for k in result.claim_stability:
            pars = "; ".join(f"`{p}` {v:.4g}" for p, v in k.values.items())
            lines.append(f"| {k.effect} | {k.dropped_run + 1} | {pars} | {changes(k.verdict)} | "
                         f"{'excluded' if k.on_run is None else changes(k.on_run)} | {'yes' if k.significant else 'no'} |")
        for note in instability_notes(result):
            lines += ["", note]
    if result.other_cross_run:
        lines += ["", "## `other` across runs", "",
                  "`other` refitted without each training run and judged by the keep test on that run's windows, "
                  "each run with its own run-level values (docs/sysid.md, \"Fallback `other`\").", "",
                  "| run left out and predicted | terms | position / heading / speed vs without them | keep |",
                  "|---|---|---|---|"]
        for k in result.other_cross_run:
            terms = "; ".join(f"`{n}` {v:.4g}" for n, v in k.params.items()) or "none"
            lines.append(f"| {Path(result.traj.runs[k.run].source).name} | {terms} | "
                         f"{100 * k.verdict.heldout_error_reduction:.1f} / {100 * k.verdict.heading_reduction:+.1f} / "
                         f"{100 * k.verdict.speed_reduction:+.1f} % | {'yes' if k.significant else 'no'} |")
        for note in other_cross_run_notes(result):
            lines += ["", note]
    for p in result.run_level:
        lines += run_level_lines(result, p)
    lines += ["", "## Identified effects", ""]
    if result.selected:
        lines += ["Best first. Held-out reduction against the nominal dynamic model: (RMSE of the final model "
                  "refitted without the effect − RMSE of the final model) / RMSE of the nominal dynamic model. "
                  "Against the model without it: 1 − RMSE_final / RMSE_without (the significance test). Parameters "
                  "from the final joint fit.", "",
                  "| effect | parameters | held-out reduction vs nominal dynamic | vs model without it |",
                  "|---|---|---|---|"]
        for e in result.selected:
            lines.append(f"| {e.effect} | {_fmt_params(e.params, e.params_std)} | "
                         f"{100 * e.reduction_vs_nominal:.1f} % | {100 * e.heldout_error_reduction:.1f} % |")
        if result.unnamed_effect_remains:
            lines += ["", "The `other` terms are written to the car file's `[other_terms]` table "
                      "(`accel_<term>`, `yaw_rate_<term>`; vehicles/extra_terms.py)."]
    else:
        lines.append("None.")
    lines += ["", "## Corrections written", "", "| field | before | after |", "|---|---|---|"]
    for f in result.car_in.corrections.__dataclass_fields__:
        a, b = getattr(result.car_in.corrections, f), getattr(result.car_out.corrections, f)
        lines.append(f"| `{f}` | {a:.5g} | {b:.5g} |")
    lines += ["", "## Residual against its explaining variable", ""]
    for effect, path in plots:
        rel = Path(os.path.relpath(path.resolve(), report_dir.resolve()))
        lines += [f"![{effect}]({rel.as_posix()})", ""]
    assert all(e.effect in EFFECT_NAMES for e in result.selected)
    return "\n".join(lines) + "\n"
