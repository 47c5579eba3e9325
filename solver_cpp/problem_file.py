"""JSON problem files (docs/problem-format.md): load into a GameProblem + settings + initial guess,
and write problems and results. Errors name the field at fault."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from .models import KinematicBicycle, LinearModel
from .problem import Agent, Collision, GameProblem, Obstacle, QuadraticCost
from .solve import GameResult, WarmStart, make_settings

DYNAMICS_TYPES = ("kinematic_bicycle", "linear")


class ProblemFileError(ValueError):
    """A problem file that cannot be used; the message names the field."""


def _get(d: dict, key: str, where: str, required: bool = True, default: Any = None):
    if not isinstance(d, dict):
        raise ProblemFileError(f"{where} must be a JSON object")
    if key not in d:
        if required:
            raise ProblemFileError(f"{where}.{key} is missing" if where else f"{key} is missing")
        return default
    return d[key]


def _numbers(value, where: str, shape: tuple | None = None) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ProblemFileError(f"{where} must be numbers") from None
    if shape is not None and arr.shape != shape:
        raise ProblemFileError(f"{where} must have shape {list(shape)}, got {list(arr.shape)}")
    return arr


def problem_from_dict(data: dict) -> tuple[GameProblem, dict, WarmStart | None]:
    """Returns (problem, solver settings overrides, initial guess or None)."""
    if not isinstance(data, dict):
        raise ProblemFileError("the problem file must contain a JSON object")
    dt = _get(data, "dt", "")
    horizon = _get(data, "horizon", "")
    if not isinstance(dt, (int, float)) or isinstance(dt, bool) or not math.isfinite(dt) or dt <= 0:
        raise ProblemFileError(f"dt must be a positive number, got {dt!r}")
    if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
        raise ProblemFileError(f"horizon must be a positive integer, got {horizon!r}")
    agents_raw = _get(data, "agents", "")
    if not isinstance(agents_raw, list) or not agents_raw:
        raise ProblemFileError("agents must be a non-empty list")
    agents, u_init = [], []
    for i, a in enumerate(agents_raw):
        w = f"agents[{i}]"
        dyn = _get(a, "dynamics", w)
        typ = _get(dyn, "type", f"{w}.dynamics")
        if typ == "kinematic_bicycle":
            model = KinematicBicycle(lf=_get(dyn, "lf", f"{w}.dynamics"), lr=_get(dyn, "lr", f"{w}.dynamics"))
        elif typ == "linear":
            model = LinearModel(A=_numbers(_get(dyn, "A", f"{w}.dynamics"), f"{w}.dynamics.A"),
                                B=_numbers(_get(dyn, "B", f"{w}.dynamics"), f"{w}.dynamics.B"))
        else:
            raise ProblemFileError(f"{w}.dynamics.type must be one of {DYNAMICS_TYPES}, got {typ!r}")
        c = _get(a, "cost", w)
        cost = QuadraticCost(x_ref=_get(c, "x_ref", f"{w}.cost"), Q_ref=_get(c, "Q_ref", f"{w}.cost"),
                             R=_get(c, "R", f"{w}.cost"), Q=_get(c, "Q", f"{w}.cost", False),
                             Qf_ref=_get(c, "Qf_ref", f"{w}.cost", False), Qf=_get(c, "Qf", f"{w}.cost", False))
        agents.append(Agent(dynamics=model, x0=_get(a, "x0", w), cost=cost,
                            u_min=_get(a, "u_min", w, False), u_max=_get(a, "u_max", w, False),
                            x_min=_get(a, "x_min", w, False), x_max=_get(a, "x_max", w, False),
                            lead_weight=_get(a, "lead_weight", w, False, 0.0), lead_index=_get(a, "lead_index", w, False, 0)))
        u_init.append(_get(a, "u_init", w, False))
    col = data.get("collision")
    collision = None
    if col is not None:
        collision = Collision(min_distance=_get(col, "min_distance", "collision"), form=col.get("form", "distance"),
                              enabled=bool(col.get("enabled", True)))
    obstacles = []
    for n, o in enumerate(data.get("obstacles", []) or []):
        obstacles.append(Obstacle(positions=_numbers(_get(o, "positions", f"obstacles[{n}]"), f"obstacles[{n}].positions"),
                                  min_distance=_get(o, "min_distance", f"obstacles[{n}]")))
    problem = GameProblem(dt=float(dt), horizon=horizon, agents=agents, collision=collision, obstacles=obstacles)
    problem.to_core()  # validates every field now, with names
    settings = data.get("solver", {}) or {}
    if not isinstance(settings, dict):
        raise ProblemFileError("solver must be a JSON object of solver settings")
    make_settings(**settings)  # validates names and values
    warm = None
    if any(u is not None for u in u_init):
        nu = agents[0].dynamics.nu
        U = np.zeros((len(agents), horizon, nu))
        for i, u in enumerate(u_init):
            if u is not None:
                U[i] = _numbers(u, f"agents[{i}].u_init", (horizon, nu))
                if not np.all(np.isfinite(U[i])):
                    raise ProblemFileError(f"agents[{i}].u_init has non-finite values")
        warm = WarmStart(u=U)
    return problem, settings, warm


def load_problem(path: str | Path) -> tuple[GameProblem, dict, WarmStart | None]:
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ProblemFileError(f"cannot read {path}: {exc.strerror}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ProblemFileError(f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
    try:
        return problem_from_dict(data)
    except ValueError as exc:
        raise ProblemFileError(f"{path}: {exc}") from None


def problem_to_dict(problem: GameProblem, solver: dict | None = None) -> dict:
    agents = []
    for a in problem.agents:
        d = a.dynamics
        if isinstance(d, KinematicBicycle):
            dyn = {"type": "kinematic_bicycle", "lf": d.lf, "lr": d.lr}
        elif isinstance(d, LinearModel):
            dyn = {"type": "linear", "A": np.asarray(d.A).tolist(), "B": np.asarray(d.B).tolist()}
        else:
            raise ValueError(f"dynamics type {d.type!r} has no problem-file form")
        c = a.cost
        cost = {k: list(map(float, v)) for k, v in
                dict(x_ref=c.x_ref, Q_ref=c.Q_ref, Q=c.Q, R=c.R, Qf_ref=c.Qf_ref, Qf=c.Qf).items() if v is not None}
        entry = {"dynamics": dyn, "x0": list(map(float, a.x0)), "cost": cost}
        for name in ("u_min", "u_max", "x_min", "x_max"):
            if getattr(a, name) is not None:
                entry[name] = list(map(float, getattr(a, name)))
        if a.lead_weight:
            entry["lead_weight"], entry["lead_index"] = a.lead_weight, a.lead_index
        agents.append(entry)
    out: dict = {"dt": problem.dt, "horizon": problem.horizon}
    if problem.collision is not None:
        out["collision"] = {"min_distance": _number_or_list(problem.collision.min_distance), "form": problem.collision.form}
    out["agents"] = agents
    if problem.obstacles:
        out["obstacles"] = [{"positions": np.asarray(o.positions).tolist(), "min_distance": _number_or_list(o.min_distance)}
                            for o in problem.obstacles]
    if solver:
        out["solver"] = solver
    return out


def result_to_dict(result: GameResult) -> dict:
    """The CLI's public result format (keys and units are stable: times in seconds, metres, radians)."""
    return {
        "status": result.status,
        "iterations": int(result.iterations),
        "residual_norm": float(result.residual_norm),
        "max_violation": float(result.max_violation),
        "solve_time_s": float(result.solve_time_s),
        # per agent, smallest reduced-Hessian eigenvalue; null = no free direction (inf)
        "second_order": [float(v) if np.isfinite(v) else None for v in result.second_order],
        "x": result.x.tolist(),
        "u": result.u.tolist(),
        "residual_history": result.residual_history.tolist(),
        "timings_s": {"assembly": result.assembly_time_s, "linear_solve": result.linear_solve_time_s,
                      "line_search": result.line_search_time_s, "setup": result.setup_time_s,
                      "update": result.update_time_s},
    }


def _number_or_list(value):
    """d_min as written to a problem file: a number, or a list of per-step numbers."""
    arr = np.asarray(value, dtype=float)
    return float(arr) if arr.ndim == 0 else arr.tolist()
