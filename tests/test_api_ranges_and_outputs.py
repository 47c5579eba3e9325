"""Issue 17 gaps: integers beyond the C++ int given through the Python API get an error naming the field
(not pybind11's "Invoked with"), and benchmark outputs are written atomically and checked before the run."""
import dataclasses
import os
import re

import numpy as np
import pytest

from app.cli import main
from bench.baselines import solve_algames, solve_ilqgames
from bench.merging import merging_problem
from bench.report import write_section
from solver_cpp import Solver, make_settings, solve


@pytest.mark.parametrize("horizon", [2**31, 2**40, np.int64(2**31), 0, -5])
def test_horizon_beyond_the_cpp_int_names_the_field(horizon):
    problem = dataclasses.replace(merging_problem(2, 0), horizon=horizon)
    for call in (solve, Solver, solve_ilqgames, solve_algames):
        with pytest.raises(ValueError, match="^horizon must be a positive integer"):
            call(problem)


@pytest.mark.parametrize("call,field", [
    (lambda: make_settings(max_iter=2**31), "solver.max_iter"),
    (lambda: make_settings(linear=dict(lscg_max_iter=-2**40)), "solver.linear.lscg_max_iter"),
    (lambda: solve_ilqgames(merging_problem(2, 0), max_iter=2**31), "ilqgames.max_iter"),
    (lambda: solve_algames(merging_problem(2, 0), max_iter=2**63), "algames.max_iter"),
    (lambda: solve_algames(merging_problem(2, 0), max_iter=1.5), "algames.max_iter"),
    (lambda: solve_ilqgames(merging_problem(2, 0), tol=float("nan")), "ilqgames.tol"),
    (lambda: solve_ilqgames(merging_problem(2, 0), nonsense=1), "ilqgames.nonsense"),
])
def test_out_of_range_settings_name_the_field(call, field):
    with pytest.raises(ValueError) as info:
        call()
    message = str(info.value)
    assert message.startswith(field), message
    assert "Invoked with" not in message


@pytest.mark.parametrize("argv", [
    ["bench", "merge", "--family", "all", "--cars", "2", "--instances", "1", "--no-docs"],
    ["bench", "merge", "--cars", "2", "--instances", "1", "--no-docs"],
    ["bench", "saddles", "--cases", "head-on:2:2", "--no-docs"],
])
def test_bench_json_path_is_checked_before_the_run(tmp_path, capsys, argv):
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    assert main([*argv, "--json", str(blocker / "out.json")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: cannot write") and "a-file" in err
    assert sorted(os.listdir(tmp_path)) == ["a-file"]


def test_bench_merge_no_docs_writes_no_figures(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["bench", "merge", "--cars", "2", "--instances", "1", "--solvers", "rd3g", "--no-docs"]) == 0
    assert os.listdir(tmp_path) == []
    assert main(["bench", "merge", "--cars", "2", "--instances", "1", "--solvers", "rd3g", "--no-docs",
                 "--figures", "figs"]) == 0
    assert sorted(os.listdir(tmp_path / "figs")) == ["merge_3cars.png", "merge_8cars.png", "merge_times.png"]


def test_benchmarks_md_holds_each_generated_block_once():
    # write_section rewrites every copy of a block, so a second copy would silently repeat the first.
    from bench.report import BENCHMARKS_MD
    starts = re.findall(r"<!-- ([\w.-]+):start -->", BENCHMARKS_MD.read_text())
    assert starts and len(starts) == len(set(starts)), sorted(n for n in starts if starts.count(n) > 1)


def test_family_runs_keep_a_block_per_selection_and_variant():
    # The tuned group keeps the blocks docs/benchmarks.md has; the held-out group and a steering-bounded variant get
    # their own, so that recording one does not overwrite another.
    import argparse
    import math

    from app.commands.bench import _families_section

    def name(family, solvers, bound=math.inf, rounds=0):
        return _families_section(argparse.Namespace(family=family, best_response_rounds=rounds), solvers, bound)

    three = ["rd3g", "ilqgames", "algames"]
    assert name("tuned", ["rd3g"]) == "merge-families"
    assert name("tuned", three) == "merge-families-rd3g-ilqgames-algames"
    assert name("held-out", three) == "merge-families-held-out-rd3g-ilqgames-algames"
    assert name("held-out", three, 0.6) == "merge-families-held-out-rd3g-ilqgames-algames-steering-bound-0.6"
    assert name("ring, four-way", ["rd3g"], rounds=2) == "merge-families-ring-four-way-best-response-2"


def test_family_tables_name_a_selection_other_than_the_tuned_group(capsys):
    assert main(["bench", "merge", "--family", "ring", "--cars", "2", "--seeds", "50:51", "--repeat", "1",
                 "--no-docs"]) == 0
    assert "## Game families: RD3G beyond the authors' merging benchmark (ring)\n" in capsys.readouterr().out


def test_write_section_replaces_the_block_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "bench.md"
    write_section("x", "first", path)
    write_section("x", "second", path)
    text = path.read_text()
    assert "second" in text and "first" not in text
    assert os.listdir(tmp_path) == ["bench.md"]
