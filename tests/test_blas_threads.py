"""`python -m app` runs numpy's BLAS on one thread (app/__init__.py): a matrix product leaves no helper threads
behind to spin and be counted in the benchmarks' CPU time."""
import os
import subprocess
import sys

import pytest

_COUNT_THREADS = ("import app, numpy as np, os; a = np.ones((400, 400)); a @ a; "
                  "print(len(os.listdir('/proc/self/task')))")


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs Linux /proc")
def test_app_keeps_blas_to_one_thread():
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    out = subprocess.run([sys.executable, "-c", _COUNT_THREADS], env=env, capture_output=True, text=True, check=True)
    assert int(out.stdout.strip()) == 1


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="needs Linux /proc")
def test_a_users_blas_setting_is_kept():
    env = dict(os.environ, OPENBLAS_NUM_THREADS="2")
    code = "import app, os; print(os.environ['OPENBLAS_NUM_THREADS'])"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "2"
