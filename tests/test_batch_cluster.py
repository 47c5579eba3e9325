"""`batch --cluster ADDRESS`: the races dispatched to a Dask distributed cluster (a LocalCluster started
here) give the same records as the local runner for the same seeds; connection and worker errors are
reported clearly. Races are cut to 1 s of race time (--max-time) to keep the file cheap."""
import json
import math
import socket
import sys

import pytest

distributed = pytest.importorskip("distributed")

from app.cli import UserError, build_parser  # noqa: E402
from app.commands.batch import CELLS, RaceFailed, run_races  # noqa: E402

MAX_TIME_S = 1.0
SEED = 7
# Wall-clock planner times differ from run to run; everything else in a record is deterministic.
TIMING_KEYS = {"solve_ms_p50", "solve_ms_p99"}


@pytest.fixture(scope="module")
def cluster():
    # Random ports (shared machine). Two single-threaded worker processes: the races really cross a
    # process boundary (workers import the project themselves) and can finish out of submission order.
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address="127.0.0.1:0", scheduler_port=0) as c:
        yield c


def batch_args(tmp_path, name, *extra):
    out = tmp_path / f"{name}.json"
    argv = ["batch", "--races", "1", "--seed", str(SEED), "--max-time", str(MAX_TIME_S), "--json", str(out), *extra]
    return build_parser().parse_args(argv), out


def run_batch(tmp_path, name, *extra):
    args, out = batch_args(tmp_path, name, *extra)
    assert args.func(args) == 0
    return json.loads(out.read_text())


def test_cluster_records_equal_local_records(cluster, tmp_path):
    local = run_batch(tmp_path, "local", "--workers", "1")
    remote = run_batch(tmp_path, "cluster", "--cluster", cluster.scheduler_address)
    # One race per cell, in the grid's order (not completion order), with the seed asked for.
    assert [(r["start"], r["speed"], r["seed"]) for r in remote["races"]] == [(s, v, SEED) for s, v in CELLS]
    # The cells' races differ (their own starts and speeds), so a record swapped between cells would show; in
    # 1 s the two front cells can end alike (the gap only grows from the start: the same minimum gap).
    outcomes = {json.dumps({k: v for k, v in r.items() if k not in ("start", "speed")}, sort_keys=True)
                for r in local["races"]}
    assert len(outcomes) >= len(CELLS) - 1
    assert remote["races"] == local["races"]
    strip = [{k: v for k, v in c.items() if k not in TIMING_KEYS} for c in local["cells"]]
    assert [{k: v for k, v in c.items() if k not in TIMING_KEYS} for c in remote["cells"]] == strip
    # Nobody completes a lap in 1 s from a standing start: every race ran to the time cap.
    period = 1.0 / 30.0
    for r in remote["races"]:
        assert r["winner"] is None
        assert r["control_steps"] == math.ceil(MAX_TIME_S / period)


def test_failing_race_on_worker_names_cell_and_seed(cluster, tmp_path):
    args, _ = batch_args(tmp_path, "bad")
    # A start the race setup rejects: passes the client but raises on the worker.
    jobs = [(args, ("middle", "fast"), 2, 2.0, 1.6, False)]
    with pytest.raises(RaceFailed, match=r"race middle/fast seed 9 failed: UserError: --start: must be one of"):
        run_races(jobs, cluster=cluster.scheduler_address)
    with pytest.raises(RaceFailed, match=r"race middle/fast seed 9 failed"):
        run_races(jobs)  # the local runner reports it the same way


# Preload for a worker that does not have the project installed: `app` cannot be imported there.
NO_PROJECT_PRELOAD = """
import sys


class _NoProject:
    def find_spec(self, name, path=None, target=None):
        if name == "app" or name.startswith("app."):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


def dask_setup(worker):
    for name in [m for m in sys.modules if m == "app" or m.startswith("app.")]:
        del sys.modules[name]
    sys.meta_path.insert(0, _NoProject())
"""


def test_worker_without_the_project_is_a_user_error(tmp_path):
    """Dask would drop such a worker on the first task and wait for another forever; the batch checks
    the import on every worker first and says what to install."""
    preload = tmp_path / "no_project_preload.py"
    preload.write_text(NO_PROJECT_PRELOAD)
    args, _ = batch_args(tmp_path, "x")
    jobs = [(args, ("front", "fast"), 0, 2.0, 1.6, False)]
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address="127.0.0.1:0",
                                  scheduler_port=0, preload=[str(preload)]) as c:
        with pytest.raises(UserError, match=r"1 of 1 workers cannot import the project .*ModuleNotFoundError.*"
                                            r"pip install \.\[cluster\]"):
            run_races(jobs, cluster=c.scheduler_address)


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_scheduler_is_a_user_error(tmp_path):
    address = f"tcp://127.0.0.1:{_closed_port()}"
    args, _ = batch_args(tmp_path, "x", "--cluster", address, "--cluster-timeout", "1")
    with pytest.raises(UserError, match=r"--cluster: no Dask scheduler answered at 'tcp://127\.0\.0\.1:\d+' within 1 s"):
        args.func(args)


def test_server_that_never_answers_times_out(tmp_path):
    """A port that accepts connections but never speaks Dask (Dask's own timeout does not cover the
    handshake, so without the batch's deadline this would block forever)."""
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen()  # the kernel completes the TCP handshake; nobody ever reads or answers
        address = f"tcp://127.0.0.1:{silent.getsockname()[1]}"
        args, _ = batch_args(tmp_path, "x", "--cluster", address, "--cluster-timeout", "1")
        with pytest.raises(UserError, match="no Dask scheduler answered .* within 1 s"):
            args.func(args)


def test_malformed_address_is_a_user_error(tmp_path):
    args, _ = batch_args(tmp_path, "x", "--cluster", "scheduler-host")
    with pytest.raises(UserError, match="'scheduler-host' is not a Dask address"):
        args.func(args)


def test_cluster_with_workers_is_rejected(tmp_path):
    args, _ = batch_args(tmp_path, "x", "--cluster", "tcp://127.0.0.1:8786", "--workers", "2")
    with pytest.raises(UserError, match="--workers .* cannot be combined with --cluster"):
        args.func(args)


def test_missing_dask_says_how_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # makes `import distributed` raise ImportError
    args, _ = batch_args(tmp_path, "x", "--cluster", "tcp://127.0.0.1:8786")
    with pytest.raises(UserError, match=r"pip install \.\[cluster\]"):
        args.func(args)
