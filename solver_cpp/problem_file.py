"""JSON problem files (docs/problem-format.md): load into a GameProblem + settings + initial guess,
and write problems and results. The file's schema is derived from the problem dataclasses
(fileio.schema); errors name the file and the field at fault."""
from __future__ import annotations

from pathlib import Path

import numpy as np

import fileio
from fileio import Array, FieldSpec, ListOf, Number, String, Table, Tagged

from . import _core
from .models import KinematicBicycle, LinearModel
from .problem import Agent, Collision, GameProblem, Obstacle, PairDistance, QuadraticCost
from .solve import (FLAT_SETTING_NAMES, REMOVED_SETTING_NAMES, SETTING_GROUPS, GameResult, WarmStart, grouped_settings,
                    settings_dict)

MAX_FILE_BYTES = 64 * 2**20


class ProblemFileError(fileio.InputFileError):
    """A problem file that cannot be used; the message names the file and the field."""


# The file schema is derived from the dataclasses in problem.py/models.py (one field list); below are
# only the constraints their types do not carry, and the file-only keys (u_init, solver).
_INDEX = Number(integer=True, ge=0, le=fileio.schema.INT32_MAX)
_DISTANCE = fileio.AnyOf((Number(gt=0), Array(1, Number(gt=0))))
_BOUND = Array(1, Number(allow_inf=True))


def _setting_spec(default, choices):
    if isinstance(default, bool):
        return fileio.Boolean()
    if isinstance(default, int):
        return Number(integer=True, ge=-fileio.schema.INT32_MAX, le=fileio.schema.INT32_MAX)
    if isinstance(default, float):
        return Number()
    return String(choices=choices)  # a C++ enum, named by its value


def _settings_table(settings, where: str, flat: dict) -> Table:
    """The fields of a C++ settings struct (or group) by name, typed by its defaults; groups nest."""
    fields = {}
    for name, default in settings_dict(settings).items():
        if name in SETTING_GROUPS:
            spec = _settings_table(getattr(settings, name), f"{where}.{name}", {})
        else:
            spec = _setting_spec(default, tuple(getattr(type(getattr(settings, name)), "__members__", ())))
        fields[name] = FieldSpec(spec, required=False)
    for old, new in flat.items():  # the previous release's flat names (deprecated), typed as their new field
        group, name = new.split(".")
        value = getattr(getattr(settings, group), name)
        spec = _setting_spec(settings_dict(getattr(settings, group))[name],
                             tuple(getattr(type(value), "__members__", ())))
        if old in fields:  # "barrier": a group, or the old barrier-form name
            spec = fileio.AnyOf((fields[old].spec, spec))
        fields[old] = FieldSpec(spec, required=False)
    return Table(fields, where)


def _solver_table() -> Table:
    """Every C++ solver setting by its grouped name (docs/problem-format.md), the deprecated flat names, and the
    removed settings' names (accepted and ignored with a warning, typed as before)."""
    table = _settings_table(_core.Settings(), "solver", FLAT_SETTING_NAMES)
    removed = {name: FieldSpec(_setting_spec(value, ()), required=False) for name, value in REMOVED_SETTING_NAMES.items()}
    return Table({**table.fields, **removed}, table.name)


def _schema() -> Table:
    table = fileio.table_from_dataclass
    dynamics = Tagged("type", {
        "kinematic_bicycle": table(KinematicBicycle, overrides={"lf": Number(gt=0), "lr": Number(gt=0)}),
        "linear": table(LinearModel, overrides={"A": Array(2, min_len=1), "B": Array(2, min_len=1)}),
    })
    cost = table(QuadraticCost, overrides={**{k: Array(1, Number(ge=0)) for k in ("Q_ref", "R", "Q", "Qf_ref", "Qf")},
                                           "x_ref_steps": Array(2, min_len=1)})
    agent = table(Agent, overrides={
        "dynamics": dynamics, "cost": cost, "lead_index": _INDEX,
        **{k: _BOUND for k in ("u_min", "u_max", "x_min", "x_max")}},
        extra={"u_init": FieldSpec(Array(2), required=False, nullable=True)})
    pair_distance = table(PairDistance, overrides={"agents": Array(1, _INDEX, length=2), "min_distance": _DISTANCE})
    collision = table(Collision, overrides={"min_distance": _DISTANCE, "form": String(choices=("distance", "squared")),
                                            "pos_x": _INDEX, "pos_y": _INDEX,
                                            "pair_distances": ListOf(pair_distance),
                                            "pos_x_scale": Array(1, Number(gt=0))})
    obstacle = table(Obstacle, overrides={"positions": Array(2), "min_distance": _DISTANCE})
    return table(GameProblem, overrides={
        "dt": Number(gt=0), "horizon": Number(integer=True, ge=1, le=fileio.schema.INT32_MAX),
        "agents": ListOf(agent, min_len=1), "collision": collision, "obstacles": ListOf(obstacle)},
        nullable=("obstacles",),  # "obstacles": null has always meant none
        extra={"solver": FieldSpec(_solver_table(), required=False, nullable=True)})


PROBLEM_SCHEMA = _schema()


def problem_from_dict(data, source: str = "<problem>") -> tuple[GameProblem, dict, WarmStart | None]:
    """Returns (problem, solver settings overrides, initial guess or None)."""
    d = fileio.validate(data, PROBLEM_SCHEMA, source, ProblemFileError)
    agents, u_init = [], []
    for a in d["agents"]:
        dyn = a.pop("dynamics")
        kind = dyn.pop("type")
        model = KinematicBicycle(**dyn) if kind == "kinematic_bicycle" else \
            LinearModel(A=np.asarray(dyn["A"], float), B=np.asarray(dyn["B"], float))
        u_init.append(a.pop("u_init", None))
        agents.append(Agent(dynamics=model, cost=QuadraticCost(**a.pop("cost")), **a))
    collision = None
    if "collision" in d:
        pairs = [PairDistance(agents=tuple(q["agents"]), min_distance=q["min_distance"])
                 for q in d["collision"].pop("pair_distances", [])]
        collision = Collision(**d["collision"], pair_distances=pairs)
    obstacles = [Obstacle(positions=np.asarray(o["positions"], float), min_distance=o["min_distance"])
                 for o in d.get("obstacles", [])]
    horizon = d["horizon"]
    problem = GameProblem(dt=d["dt"], horizon=horizon, agents=agents, collision=collision, obstacles=obstacles)
    settings = grouped_settings(d.get("solver") or {}, stacklevel=2, source=f"{source}: ")
    try:
        problem.to_core()  # sizes and cross-field rules, with names
    except ValueError as exc:
        raise ProblemFileError(f"{source}: {exc}") from None
    warm = None
    if any(u is not None for u in u_init):
        nu = agents[0].dynamics.nu
        U = np.zeros((len(agents), horizon, nu))
        for i, u in enumerate(u_init):
            if u is not None:
                u = np.asarray(u, float)
                if u.shape != (horizon, nu):
                    raise ProblemFileError(f"{source}: agents[{i}].u_init: expected shape [{horizon}, {nu}] "
                                           f"(horizon rows of nu controls), got {list(u.shape)}")
                U[i] = u
        warm = WarmStart(u=U)
    return problem, settings, warm


def load_problem(path: str | Path) -> tuple[GameProblem, dict, WarmStart | None]:
    data = fileio.load_json(path, "problem file", max_bytes=MAX_FILE_BYTES, error=ProblemFileError)
    return problem_from_dict(data, str(path))


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
        if c.x_ref_steps is not None:
            cost["x_ref_steps"] = np.asarray(c.x_ref_steps, dtype=float).tolist()
        entry = {"dynamics": dyn, "x0": list(map(float, a.x0)), "cost": cost}
        for name in ("u_min", "u_max", "x_min", "x_max"):
            if getattr(a, name) is not None:
                entry[name] = list(map(float, getattr(a, name)))
        if a.lead_weight:
            entry["lead_weight"], entry["lead_index"] = a.lead_weight, a.lead_index
        agents.append(entry)
    out: dict = {"dt": problem.dt, "horizon": problem.horizon}
    col = problem.collision
    if col is not None:
        out["collision"] = {"min_distance": _number_or_list(col.min_distance), "form": col.form,
                            "enabled": col.enabled, "pos_x": col.pos_x, "pos_y": col.pos_y}
        if col.pos_x_scale is not None:
            out["collision"]["pos_x_scale"] = [float(a) for a in col.pos_x_scale]
        if col.pair_distances:
            out["collision"]["pair_distances"] = [{"agents": [int(a) for a in q.agents],
                                                   "min_distance": _number_or_list(q.min_distance)}
                                                  for q in col.pair_distances]
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
        # conflicting pairs of the initial guess and their order at the result; the passing-order search's candidates
        "passing_order": result.passing_order,
        "orders": [{**c, "guess_residual": c["guess_residual"] if np.isfinite(c["guess_residual"]) else None,
                    "u": None if c["u"] is None else c["u"].tolist()} for c in result.orders],
        "other_orders": result.other_orders,
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
