"""Markdown report, residual plots and the JSON summary of an identification run."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

import fileio

from sysid.diagnose import EFFECT_NAMES, ErrorSummary, Fit, SysidResult

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
    "motor_drift": ("time since the log start [s]", "speed error at horizon [m/s]"),
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
        return traj.t[starts] - traj.t[0]
    if effect == "tire_slip":
        return np.mean(v * traj.yaw_rate[window], axis=1)
    if effect == "longitudinal_drag":
        return np.mean(v * np.abs(v), axis=1)
    return np.mean(v, axis=1)


def residual_for(fit: Fit, effect: str) -> np.ndarray:
    e = fit.heldout_errors
    if effect == "tire_slip":
        return e.lateral[:, -1]
    if effect in ("longitudinal_drag", "motor_drift"):
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
    }


def write_json(result: SysidResult, path: Path, car_params_out: str) -> Path:
    fileio.atomic_write_text(path, json.dumps(result_json(result, car_params_out), indent=2) + "\n", stream=True)
    return path


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
    lines += [
        f"* Log: `{log_path}` — {traj.n_raw_rows} rows, {traj.n_duplicates_merged} duplicate timestamps merged, "
        f"{traj.n_gaps} gap(s); {traj.n} samples on a {traj.dt * 1000:.2f} ms grid "
        f"({traj.t[-1] - traj.t[0]:.1f} s)" + (f"; {log_note}." if log_note else "."),
        f"* Car parameters in: `{car_in}`; out: `{car_out}`" + (f"; JSON: `{json_path}`." if json_path else "."),
        f"* Horizon {result.horizon_steps} steps ({result.horizon_steps * traj.dt:.2f} s); "
        f"{result.split.train.size} training and {result.split.heldout.size} held-out windows "
        f"(time blocks, every {s.heldout_every}rd held out).",
        f"* Estimated measurement noise: position {traj.position_noise_m * 1000:.1f} mm, heading "
        f"{traj.heading_noise_rad:.4f} rad.",
        "",
        "## Verdict",
        "",
    ]
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
        "## Candidates",
        "",
        "Each candidate fitted alone on the training blocks on top of the reference model; reduction = "
        "1 − RMSE_after / RMSE_before of the held-out horizon position error; confidence = block-bootstrap "
        "probability that the held-out mean squared error went down. Standard deviations are cluster-robust "
        "(sandwich) estimates from the least-squares Jacobian.",
        "",
        "| effect | fitted parameters | held-out reduction | confidence | significant |",
        "|---|---|---|---|---|",
    ]
    for c in result.candidates:
        lines.append(f"| {c.effect} | {_fmt_params(c.params, c.params_std)} | {100 * c.heldout_error_reduction:+.1f} % "
                     f"| {c.confidence:.2f} | {'yes' if c.significant else 'no'} |")
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
