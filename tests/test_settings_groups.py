"""Solver settings in their groups (solver_cpp/include/rd3g/problem.hpp): the grouped keyword form, the previous
release's flat names (accepted with a DeprecationWarning naming the new name), errors naming the grouped field,
and the same form in problem files and on the bench command line."""
import json
import re
import warnings

import pytest

from app.cli import main
from bench.merging import merging_problem
from solver_cpp import Solver, _core, make_settings, settings_dict, solve
from solver_cpp.problem_file import ProblemFileError, problem_from_dict, problem_to_dict
from solver_cpp.solve import FLAT_SETTING_NAMES, REMOVED_RULES, REMOVED_SETTING_NAMES, SETTING_GROUPS, merge_settings


def test_every_group_and_field_of_the_cpp_struct_is_reachable_and_documented_once():
    d = settings_dict(_core.Settings())
    assert set(SETTING_GROUPS) <= set(d) and all(isinstance(d[g], dict) for g in SETTING_GROUPS)
    grouped = {f"{g}.{f}" for g in SETTING_GROUPS for f in d[g]}
    # every flat name of the previous release maps onto an existing grouped field, each field at most once
    assert set(FLAT_SETTING_NAMES.values()) <= grouped
    assert len(set(FLAT_SETTING_NAMES.values())) == len(FLAT_SETTING_NAMES)
    header = open("solver_cpp/include/rd3g/problem.hpp").read()
    for g in SETTING_GROUPS:
        for f in d[g]:
            assert f" {f} = " in header, f"{g}.{f} has no default in problem.hpp"


def test_grouped_override_changes_that_field_only():
    defaults = settings_dict(_core.Settings())
    s = make_settings(tol=1e-4, stall=dict(window=5, crawl_ratio=0.25), linear=dict(solver="sparse_lu"))
    got = settings_dict(s)
    assert (s.tol, s.stall.window, s.stall.crawl_ratio, s.linear.solver) == (1e-4, 5, 0.25, _core.LinearSolver.sparse_lu)
    expected = {**defaults, "tol": 1e-4, "stall": {**defaults["stall"], "window": 5, "crawl_ratio": 0.25},
                "linear": {**defaults["linear"], "solver": "sparse_lu"}}
    assert got == expected


@pytest.mark.parametrize("flat, group, field, value", [
    ("restarts", "restart", "count", 3), ("stall_window", "stall", "window", 4),
    ("saddle_escapes", "second_order", "escapes", 0), ("ls_max_steps", "line_search", "max_steps", 7),
    ("barrier", "barrier", "mode", "primal"), ("linear_solver", "linear", "solver", "sparse_qr")])
def test_flat_name_warns_naming_the_new_name_and_sets_the_same_field(flat, group, field, value):
    with pytest.warns(DeprecationWarning, match=rf"solver\.{flat} is deprecated: use solver\.{group}\.{field}"):
        old = make_settings(**{flat: value})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        new = make_settings(**{group: {field: value}})
    assert settings_dict(old) == settings_dict(new)
    assert settings_dict(new)[group][field] == value


def test_settings_surface_is_smaller_than_the_51_flat_fields_it_replaced():
    d = settings_dict(_core.Settings())
    leaves = sum(len(d[g]) for g in SETTING_GROUPS) + sum(1 for k in d if k not in SETTING_GROUPS)
    assert leaves < 51
    assert not set(REMOVED_SETTING_NAMES) & {k for k in d if k not in SETTING_GROUPS}


@pytest.mark.parametrize("name", sorted(REMOVED_SETTING_NAMES))
def test_removed_setting_warns_giving_its_fixed_value_and_changes_nothing(name):
    value = REMOVED_SETTING_NAMES[name]
    instead = re.escape(REMOVED_RULES[name]) if name in REMOVED_RULES else rf"the solver uses the fixed value {value}"
    with pytest.warns(DeprecationWarning, match=rf"solver\.{name} is deprecated and ignored: {instead}"):
        s = make_settings(**{name: 3 * value})
    assert settings_dict(s) == settings_dict(_core.Settings())


def test_problem_file_accepts_a_removed_setting_with_a_warning():
    data = problem_to_dict(merging_problem(2, 0), solver={"tol": 1e-4})
    data["solver"]["lm_nu_init"] = 1e-5
    with pytest.warns(DeprecationWarning, match=r"p\.json: solver\.lm_nu_init is deprecated and ignored"):
        _, settings, _ = problem_from_dict(data, "p.json")
    assert settings == {"tol": 1e-4}


def test_flat_and_grouped_solves_are_the_same_solve():
    problem = merging_problem(2, 0)
    with pytest.warns(DeprecationWarning):
        old = solve(problem, restarts=0, polish_gap=0.0)
    new = solve(problem, restart=dict(count=0), stall=dict(polish_gap=0.0))
    assert (old.status, old.iterations) == (new.status, new.iterations)
    assert (old.u == new.u).all()


@pytest.mark.parametrize("overrides, message", [
    ({"stall": {"window": -1}}, "solver.stall.window must be >= 0"),
    ({"stall": {"windw": 3}}, "solver.stall.windw is not a solver setting"),
    ({"stall": 8}, "solver.stall must be a mapping"),
    ({"linear": {"solver": "cholesky"}}, "solver.linear.solver must be one of"),
    ({"second_order": {"escapes": 1.5}}, "solver.second_order.escapes must be an integer"),
    ({"best_response": {"margin": float("nan")}}, "solver.best_response.margin must be finite"),
    ({"best_response": {"restarts": -1}}, "solver.best_response.restarts must be >= 0"),
    ({"no_such_group": {"window": 1}}, "solver.no_such_group is not a solver setting"),
])
def test_bad_grouped_setting_names_the_grouped_field(overrides, message):
    with pytest.raises(ValueError, match=message.replace(".", r"\.").replace("(", r"\(")):
        make_settings(**overrides)


def test_update_settings_keeps_the_other_overrides():
    solver = Solver(merging_problem(2, 0), restart=dict(count=0), stall=dict(window=5))
    solver.update_settings(stall=dict(crawl_window=7))
    s = solver.settings
    assert (s.restart.count, s.stall.window, s.stall.crawl_window) == (0, 5, 7)


def test_merge_settings_layers_field_by_field_and_none_means_default():
    merged = merge_settings({"restart": {"count": 3, "rho_progress": 0.5}, "tol": 1e-3},
                            {"restart": {"count": None}, "tol": None, "stall": {"window": 2}})
    assert merged == {"restart": {"rho_progress": 0.5}, "stall": {"window": 2}}


def test_problem_file_takes_grouped_settings_and_warns_about_flat_ones():
    data = problem_to_dict(merging_problem(2, 0), solver={"tol": 1e-4, "stall": {"window": 6}})
    _, settings, _ = problem_from_dict(json.loads(json.dumps(data)), "p.json")
    assert settings == {"tol": 1e-4, "stall": {"window": 6}}
    assert make_settings(**settings).stall.window == 6
    data["solver"] = {"stall_window": 6, "barrier": "primal"}
    with pytest.warns(DeprecationWarning) as record:
        _, settings, _ = problem_from_dict(data, "p.json")
    assert sorted(str(w.message) for w in record) == [
        "p.json: solver.barrier is deprecated: use solver.barrier.mode",
        "p.json: solver.stall_window is deprecated: use solver.stall.window"]
    assert settings == {"stall": {"window": 6}, "barrier": {"mode": "primal"}}


@pytest.mark.parametrize("solver, field", [
    ({"stall": {"windw": 6}}, "solver.stall.windw"),
    ({"stall": {"window": "six"}}, "solver.stall.window"),
    ({"linear": {"solver": "cholesky"}}, "solver.linear.solver"),
])
def test_problem_file_error_names_the_file_and_grouped_field(solver, field):
    data = problem_to_dict(merging_problem(2, 0), solver=solver)
    with pytest.raises(ProblemFileError) as err:
        problem_from_dict(data, "p.json")
    assert "p.json" in str(err.value) and field in str(err.value)


def test_bench_setting_flag_takes_the_grouped_name(capsys):
    argv = ["bench", "merge", "--family", "authors", "--cars", "2", "--no-docs", "--rd3g-setting", "stall.window=-1"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--rd3g-setting" in err and "solver.stall.window" in err, err


def test_solve_command_reads_grouped_settings_and_warns_about_flat_ones(tmp_path, capsys):
    data = problem_to_dict(merging_problem(2, 0), solver={"stall": {"window": -1}})
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(data))
    assert main(["solve", str(bad)]) == 2
    assert f"{bad}: solver.stall.window must be >= 0" in capsys.readouterr().err
    data["solver"] = {"stall_window": 6}
    flat = tmp_path / "flat.json"
    flat.write_text(json.dumps(data))
    assert main(["solve", str(flat)]) == 0
    assert f"warning: {flat}: solver.stall_window is deprecated: use solver.stall.window" in capsys.readouterr().err
