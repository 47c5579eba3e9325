"""The C++ core under AddressSanitizer and UndefinedBehaviorSanitizer (issue 17): the extension is built once
more with -fsanitize=address,undefined in build/asan (CMake + Ninja; reruns rebuild only what changed; a cold
build is a unity build, one translation unit per target, at -O1 with line tables only, so Eigen's and pybind11's
headers are compiled twice rather than once per source file), then
a child Python process with the ASan runtime preloaded imports that build in place of the normal one and
runs the solver's tests and a short solver-API fuzz. Any sanitizer report aborts the child (halt_on_error),
so a non-zero exit with the report in its output fails this test."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BUILD = ROOT / "build" / "asan"
# -g1: line tables and function names, enough for the reports' stack traces (full -g made each pybind11 source
# compile about 30 % longer).
FLAGS = "-O1 -g1 -fsanitize=address,undefined -fno-omit-frame-pointer -fno-sanitize-recover=undefined"
SOLVER_TESTS = ["test_solver_api.py", "test_linear_solvers.py", "test_solver_indices.py", "test_solver_status.py",
                "test_solver_time_limit.py", "test_solver_update.py"]
FUZZ_EXAMPLES = 150

# Runs in the child: load the sanitized module as solver_cpp._core before the package imports its own.
PRELOAD = """
import importlib.util, sys
spec = importlib.util.spec_from_file_location("solver_cpp._core", {so!r})
module = importlib.util.module_from_spec(spec)
spec.loader.exec_module(module)
sys.modules["solver_cpp._core"] = module
import solver_cpp
assert solver_cpp._core is module
"""


def _asan_runtime() -> str | None:
    """LD_PRELOAD value: the ASan runtime and libstdc++ (Python does not link libstdc++, and without it
    preloaded ASan's __cxa_throw interceptor finds no real function and aborts on the first C++ throw)."""
    gcc = shutil.which("g++")
    if gcc is None:
        return None
    paths = [subprocess.run([gcc, f"-print-file-name={lib}"], capture_output=True, text=True).stdout.strip()
             for lib in ("libasan.so", "libstdc++.so")]
    return " ".join(paths) if all(os.path.isabs(p) and os.path.exists(p) for p in paths) else None


def _build() -> Path:
    import pybind11

    tools = {name: shutil.which(name) for name in ("cmake", "ninja")}
    runtime = _asan_runtime()
    if None in tools.values() or runtime is None:
        pytest.skip(f"needs cmake, ninja and g++'s libasan (found {tools}, libasan {runtime})")
    BUILD.mkdir(parents=True, exist_ok=True)
    # Build type None: FLAGS alone (Debug would add a full -g), and no link-time optimisation (pybind11 adds it to
    # every build type but Debug unless CMAKE_INTERPROCEDURAL_OPTIMIZATION is set). The configuration is redone only when these
    # arguments change (recorded beside the build); otherwise Ninja rebuilds what changed, or nothing.
    configure = [tools["cmake"], "-S", str(ROOT), "-B", str(BUILD), "-G", "Ninja", "-DCMAKE_BUILD_TYPE=None",
                 f"-DCMAKE_CXX_FLAGS={FLAGS}", "-DCMAKE_INTERPROCEDURAL_OPTIMIZATION=OFF",
                 "-DCMAKE_UNITY_BUILD=ON", "-DCMAKE_UNITY_BUILD_BATCH_SIZE=0",
                 f"-DPython_EXECUTABLE={sys.executable}", f"-Dpybind11_DIR={pybind11.get_cmake_dir()}"]
    stamp = BUILD / "rd3g-configure.txt"
    if not (BUILD / "build.ninja").exists() or not stamp.exists() or stamp.read_text() != "\n".join(configure):
        subprocess.run(configure, check=True, capture_output=True)
        stamp.write_text("\n".join(configure))
    # One job per core (Ninja's default, cores + 2, only adds memory pressure); a unity build has two units.
    done = subprocess.run([tools["ninja"], "-C", str(BUILD), "-j", str(os.cpu_count() or 2), "_core"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return next(BUILD.glob("_core*.so"))


def _run_sanitized(so: Path, body: str, timeout_s: float) -> subprocess.CompletedProcess:
    env = dict(os.environ, LD_PRELOAD=_asan_runtime(),
               ASAN_OPTIONS="detect_leaks=0:halt_on_error=1:abort_on_error=0",
               UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1", PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-c", PRELOAD.format(so=str(so)) + body], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout_s)


def _check(proc: subprocess.CompletedProcess) -> None:
    output = proc.stdout[-4000:] + "\n...\n" + proc.stderr[:4000] + "\n...\n" + proc.stderr[-2000:]
    assert "ERROR: AddressSanitizer" not in output and "runtime error:" not in output, output
    assert proc.returncode == 0, output


@pytest.fixture(scope="module")
def sanitized_core() -> Path:
    return _build()


def test_solver_tests_pass_under_asan_and_ubsan(sanitized_core):
    tests = [str(ROOT / "tests" / t) for t in SOLVER_TESTS]
    _check(_run_sanitized(sanitized_core, f"import pytest; sys.exit(pytest.main(['-q', '-x', '-p', 'no:cacheprovider', *{tests!r}]))",
                          timeout_s=1200))


def test_solver_api_fuzz_under_asan_and_ubsan(sanitized_core, tmp_path):
    body = (f"from pathlib import Path; from bench.fuzz import _solver_child; "
            f"r = _solver_child({FUZZ_EXAMPLES}, 1, Path({str(tmp_path)!r})); print(r); "
            f"sys.exit(1 if r['failures'] else 0)")
    _check(_run_sanitized(sanitized_core, body, timeout_s=1200))
