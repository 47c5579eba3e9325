"""Every benchmark is a subcommand of `python -m app bench` (issue 31): each one's --help, a quick run of the cheap
ones, and the old module entry points (forwarded, or naming the new command)."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from app.cli import main

ROOT = Path(__file__).resolve().parent.parent
BENCHES = ["solver", "merge", "saddles", "size", "fuzz", "loop", "race-perturbations", "baselines", "time-limit",
           "tracking", "malformed", "charuco", "track-video", "camera-profiles", "live-view", "planner-threads"]


def test_the_bench_command_lists_every_benchmark(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines() if re.match(r"    \S", line)]
    assert sorted(listed) == sorted(BENCHES)


@pytest.mark.parametrize("name", BENCHES)
def test_help(name, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["bench", name, "--help"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: python -m app bench {name} ")


def test_quick_runs(capsys):
    assert main(["bench", "baselines", "--cars", "2", "--seeds", "1"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[:2] for line in out[1:]] == [["2", "rd3g"], ["2", "ilqgames"], ["2", "algames"]]
    assert main(["bench", "time-limit", "--cars", "2", "--seeds", "1", "--limits", "0.5", "--paths", "sparse_lu"]) == 0
    rows = capsys.readouterr().out.splitlines()[1:]
    assert len(rows) == 1 and rows[0].split()[:3] == ["sparse_lu", "0.500", "0"]


def test_bad_options_exit_2(capsys):
    assert main(["bench", "race-perturbations", "--late-ms", "5", "1", "--seeds", "0"]) == 2
    assert "--late-ms: need 0 <= LO <= HI" in capsys.readouterr().err
    assert main(["bench", "malformed", "--formats", "nope"]) == 2
    assert "--formats: unknown format(s) nope" in capsys.readouterr().err
    assert main(["bench", "camera-profiles", "--frames", "0", "--no-docs"]) == 2
    assert "--frames: need at least 1" in capsys.readouterr().err


def test_old_entry_points():
    """app/ modules forward to the new command; bench/ modules (which may not import app/) name it."""
    fwd = subprocess.run([sys.executable, "-m", "app.realtime.bench", "--help"], cwd=ROOT, capture_output=True, text=True)
    assert fwd.returncode == 0 and fwd.stdout.startswith("usage: python -m app bench loop ")
    old = subprocess.run([sys.executable, "-m", "bench.race_perturbations"], cwd=ROOT, capture_output=True, text=True)
    assert old.returncode != 0 and "python -m app bench race-perturbations" in old.stderr
