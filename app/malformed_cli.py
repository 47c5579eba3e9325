"""Hand-built malformed inputs through the command line: the second malformed-input family of issue 17.

bench/fuzz.py draws random structures for each loader in-process; this family takes the project's real
files (the tracks, the car file and the fixed markers in the repository; a problem, intrinsics, a
calibration, a drive log, a link capture and a race recording written by the project's own writers; the HIL
mocap survey points),
mutates them by hand-written rules (truncation at many byte offsets, one field at a time swapped for a
value of another type, a huge number, a NaN string, deleted, nested 40 deep; CSV cells and capture
lines made non-numeric, short or odd; the whole file re-encoded as UTF-16, a Latin-1 byte or a NUL
inserted; 16 bytes of a recording flipped) and runs the command that reads them in a
child process (forked from a parent that imported the CLI once: the same process isolation as a
subprocess, without 2 s of imports per case). Each case must end in one of:

* rejected: exit code 2, a message on stderr naming the file and, for a mutation that cannot be valid,
  the place (a field of the file, or line / row / column / byte), no traceback, and no output file
  or temporary file left behind (a mutation that loads and then fails on its values, e.g. a marker
  moved so that the camera fit fails, must name the file);
* accepted: the command's normal exit code (the mutation left a file the format allows, e.g. an
  optional field deleted), with its JSON outputs complete (they parse).

Anything else (another exit code, a traceback, a signal, a timeout, a partial output) is a failure.
Some mutations can never give a valid file (a NaN string or a type swap where only numbers are
allowed, text cut inside JSON, re-encoding as UTF-16): for those acceptance is a failure too.

    python -m app bench malformed [--formats all] [--per-format N] [--seed S] [--json out.json]
"""
from __future__ import annotations

import json
import math
import os
import random
import re
import signal
import sys
import tempfile
import time
import tomllib
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from app.cli import build_parser, main as cli_main
from sim.charuco_views import BoardRenderer
from bench.fuzz import toml_bytes  # the API fuzz's TOML renderer (hypothesis: installed with the test extra)
from bench.merging import merging_problem
from fileio import atomic_write_text
from sim.camera import SyntheticCamera, overhead_camera
from solver_cpp.problem_file import problem_to_dict
from sysid.generate import generate_log
from sysid.log import write_log_csv
from tracking.calibration import Intrinsics, load_fixed_markers, save_intrinsics
from tracking.charuco import load_board_file
from vehicles.fhss import FhssEncoder, ServoCalibration
from vehicles.link_capture import LinkCapture
from vehicles.params import load_car_params
from vehicles.protocol import CarCommand

ROOT = Path(__file__).resolve().parent.parent
WORDS = re.compile(r"\b(line|row|column|byte|offset|char|position|empty|end of document)\b", re.I)
DEEP = 40  # nesting levels: above fileio.MAX_DEPTH (32)


@dataclass(frozen=True)
class Case:
    format: str
    mutation: str       # e.g. "swap agents[0].x0[1] -> 'NaN'", "truncate at byte 120"
    data: bytes
    must_reject: bool
    names: tuple[str, ...] = ()  # words one of which the message must contain (field names), else WORDS


@dataclass(frozen=True)
class Format:
    name: str
    suffix: str
    kind: str                                   # json | toml | csv | capture | binary
    argv: Callable[[Path, Path, "Seeds"], list[str]]  # (input file, empty output folder, seeds) -> CLI arguments
    accepted_codes: tuple[int, ...] = (0,)
    timeout_s: float = 120.0
    nullable: tuple[str, ...] = ()                # fields where null is a documented value (no estimate)
    flag: str | None = None                       # kind "flag": the input is this flag's value, which the message names


@dataclass
class Seeds:
    """Valid example files (bytes) per format, and the side files the commands need."""
    folder: Path
    files: dict[str, bytes] = field(default_factory=dict)
    arena_png: Path | None = None
    board_views: list[Path] = field(default_factory=list)  # rendered views of the board file's board
    intrinsics: Path | None = None
    fixed_markers: Path = ROOT / "tracking" / "data" / "oval_fixed_markers.json"


# --------------------------------------------------------------------------- the formats and commands
FORMATS = {f.name: f for f in [
    # solve exits 1 when the solver does not converge (a result, written whole).
    Format("problem", ".json", "json", lambda f, o, s: ["solve", f, "--out", o / "result.json", "--time-limit", "0.3"],
           accepted_codes=(0, 1)),
    Format("car", ".toml", "toml", lambda f, o, s: ["race", "--car-params", f, "--max-time", "0.3", "--out", o / "race.rrd",
                                                    "--json", o / "race.json"]),
    Format("track", ".json", "json", lambda f, o, s: ["race", "--track", f, "--max-time", "0.3", "--out", o / "race.rrd",
                                                      "--json", o / "race.json"]),
    Format("fixed_markers", ".json", "json", lambda f, o, s: ["calibrate", "--image", s.arena_png, "--fixed-markers", f,
                                                              "--intrinsics", s.intrinsics, "--out", o / "cal.json"]),
    Format("intrinsics", ".json", "json", lambda f, o, s: ["calibrate", "--image", s.arena_png, "--fixed-markers",
                                                           s.fixed_markers, "--intrinsics", f, "--out", o / "cal.json"]),
    # A valid calibration gets as far as the camera (an image file: one frame, then the camera check fails, exit 1).
    Format("calibration", ".json", "json", lambda f, o, s: ["check", "--calibration", f, "--camera", s.arena_png,
                                                            "--serial", os.devnull], accepted_codes=(1,),
           nullable=("focal_std_px", "focal_std_markers_px", "focal_std_principal_point_px", "reprojection_rms_px",
                     "reprojection_max_px")),
    Format("board", ".json", "json", lambda f, o, s: ["calibrate-camera", *s.board_views, "--board", f,
                                                      "--out", o / "intrinsics.json"]),
    Format("sysid_csv", ".csv", "csv", lambda f, o, s: ["sysid", f, "--car-params", "buzzracer", "--report", o / "r.md",
                                                        "--json", o / "r.json", "--fit-windows", "20"]),
    # link-decode exits 1 when the capture holds bad frames (a decode report, not an error).
    Format("link_capture", ".txt", "capture", lambda f, o, s: ["link-decode", f, "--protocol", "buzzracer-fhss", "--quiet"],
           accepted_codes=(0, 1)),
    Format("recording", ".rrd", "binary", lambda f, o, s: ["review", f, "--no-plots", "--json", o / "review.json"]),
    Format("roster", ".toml", "toml", lambda f, o, s: ["race", "--roster", f, "--max-time", "0.3", "--out", o / "race.rrd",
                                                       "--json", o / "race.json"]),
    # Roster flags: the case's "file" holds the flag's value.
    Format("cars_flag", ".txt", "flag", lambda f, o, s: ["race", "--cars", _flag_value(f), "--max-time", "0.3",
                                                         "--out", o / "race.rrd", "--json", o / "race.json"], flag="--cars"),
    Format("grid_flag", ".txt", "flag", lambda f, o, s: ["race", "--cars", "rd3g,mpc,mpc", "--grid", _flag_value(f),
                                                         "--max-time", "0.3", "--out", o / "race.rrd",
                                                         "--json", o / "race.json"], flag="--grid"),
    Format("mocap_survey", ".csv", "csv", lambda f, o, s: ["mocap-calibrate", f, "--out", o / "mocap.json"]),
]}


def _flag_value(path: Path) -> str:
    """The flag value a "flag" case wrote to its input file (the path itself where none was written)."""
    return path.read_text() if path.is_file() else str(path)


def make_seeds(folder: Path) -> Seeds:
    """The valid files: from the repository where it has one, else written by the project's own writers."""
    import cv2
    import numpy as np


    s = Seeds(folder)
    folder.mkdir(parents=True, exist_ok=True)
    s.files["problem"] = json.dumps(problem_to_dict(merging_problem(2, 0)), indent=1).encode()
    s.files["car"] = (ROOT / "vehicles" / "buzzracer.toml").read_bytes()
    s.files["track"] = (ROOT / "tracks" / "data" / "oval.json").read_bytes()
    # Without its comments and its (free-text, optional) name column: the CSV mutations take row 1 for the
    # header and every column for a required number.
    survey = (ROOT / "tracking" / "data" / "hil_mocap_survey.csv").read_bytes().splitlines(keepends=True)
    s.files["mocap_survey"] = b"".join(ln.split(b",", 1)[1] for ln in survey if not ln.startswith(b"#"))
    s.files["fixed_markers"] = s.fixed_markers.read_bytes()
    camera = overhead_camera()
    synth = SyntheticCamera(camera, fixed_markers=list(load_fixed_markers(s.fixed_markers).markers.values()))
    s.arena_png = folder / "arena.png"
    cv2.imwrite(str(s.arena_png), synth.render([], 0.0).image)
    s.intrinsics = folder / "intrinsics.json"
    save_intrinsics(s.intrinsics, Intrinsics(camera.camera_matrix, np.zeros(5), camera.image_size))
    s.files["intrinsics"] = s.intrinsics.read_bytes()
    cal = folder / "calibration.json"
    code, _, err = run_cli(["calibrate", "--image", s.arena_png, "--fixed-markers", s.fixed_markers,
                            "--intrinsics", s.intrinsics, "--out", cal], folder, 300)
    if code != 0:
        raise RuntimeError(f"calibrate on the rendered arena failed ({code}): {err}")
    s.files["calibration"] = cal.read_bytes()
    board = folder / "board.png"
    code, _, err = run_cli(["make-board", "--out", board, "--dpi", "100"], folder, 120)
    if code != 0:
        raise RuntimeError(f"make-board failed ({code}): {err}")
    s.files["board"] = board.with_suffix(".json").read_bytes()
    spec = load_board_file(board.with_suffix(".json")).board
    render = BoardRenderer((spec.squares_x, spec.squares_y), spec.square_length_m, spec.marker_length_m,
                           spec.dictionary, supersample=2)
    rng = np.random.default_rng(0)
    for i, (rvec, tvec) in enumerate(render.random_poses(4, rng, depth_m=(0.45, 0.55))):
        s.board_views.append(folder / f"board_view{i}.png")
        cv2.imwrite(str(s.board_views[-1]), render(rvec, tvec, rng=rng))
    log = folder / "drive.csv"
    write_log_csv(log, generate_log(load_car_params("buzzracer"), {}, 0.5, seed=1, physics_dt=0.002))
    s.files["sysid_csv"] = log.read_bytes()
    # Two cars' servo calibrations as tests/test_fhss_link.py writes them (modem ids 0 and 5).
    encoder = FhssEncoder([ServoCalibration(0, math.radians(27), math.radians(23.2), math.radians(29.8)),
                           ServoCalibration(5, math.radians(27), math.radians(27), math.radians(27))])
    cap = folder / "capture.txt"
    with LinkCapture(cap, clock=lambda: 0.0, origin=0.0) as capture:
        for k in range(12):
            capture.record("tx", encoder.encode(k, {5: CarCommand(0.1 * (k % 3), 0.5)}), t=0.02 * k)
        capture.record("rx", b"box\r\n", t=0.25)
    s.files["link_capture"] = cap.read_bytes()
    rec = folder / "race.rrd"
    code, _, err = run_cli(["race", "--max-time", "0.5", "--out", rec, "--json", folder / "race.json"], folder, 600)
    if code != 0:
        raise RuntimeError(f"the seed race failed ({code}): {err}")
    s.files["recording"] = rec.read_bytes()
    s.files["roster"] = ROSTER_SEED
    s.files["cars_flag"] = b"rd3g,mpc,mpc,pursuit"
    s.files["grid_flag"] = b"random"
    return s


# A four-car roster file as docs/file-formats.md ("Roster file") documents it.
ROSTER_SEED = b"""[[car]]
name = "red"
planner = "rd3g"
marker_id = 7
radio_id = 3
start_slot = 1

[[car]]
name = "blue"
planner = "mpc"
top_speed_mps = 1.7

[[car]]
name = "green"
planner = "rd3g"
reference_speed_mps = 1.5

[[car]]
name = "grey"
planner = "pursuit"
start_speed_mps = 0.5
"""


# --------------------------------------------------------------------------- running one command
def run_cli(argv: list, workdir: Path, timeout_s: float) -> tuple[int | str, str, str]:
    """`python -m app ARGV` in a forked child; (exit code or "signal N" / "timeout", stdout, stderr)."""
    workdir.mkdir(parents=True, exist_ok=True)
    out, err = workdir / ".stdout", workdir / ".stderr"
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid == 0:  # child: never returns
        code = 1
        try:
            fo = os.open(out, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            fe = os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            os.dup2(fo, 1)
            os.dup2(fe, 2)
            os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
            # New text streams on fds 1 and 2: the parent's may write elsewhere (pytest's capture).
            sys.stdout = open(1, "w", encoding="utf-8", errors="backslashreplace", closefd=False)
            sys.stderr = open(2, "w", encoding="utf-8", errors="backslashreplace", closefd=False)
            signal.signal(signal.SIGINT, signal.default_int_handler)
            try:
                code = cli_main([str(a) for a in argv])
            except SystemExit as exc:  # argparse and sys.exit: as the interpreter would report it
                code = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 1
                if isinstance(exc.code, str):
                    print(exc.code, file=sys.stderr)
            except BaseException:
                traceback.print_exc()
                code = 1
        finally:
            try:
                sys.stdout.flush()
                sys.stderr.flush()
            finally:
                os._exit(int(code) & 0xFF if isinstance(code, int) else 1)
    deadline = time.monotonic() + timeout_s
    status = None
    while True:
        done, st = os.waitpid(pid, os.WNOHANG)
        if done:
            status = os.waitstatus_to_exitcode(st)
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            status = "timeout"
            break
        time.sleep(0.01)
    code: int | str = status if status == "timeout" or status >= 0 else f"signal {-status}"
    read = lambda p: p.read_bytes().decode("utf-8", "replace") if p.exists() else ""  # noqa: E731
    return code, read(out), read(err)


# --------------------------------------------------------------------------- mutations
SWAPS: list[tuple[str, Any, bool]] = [  # (label, value, always invalid where a number is)
    ("'NaN'", "NaN", True), ("'1e999'", "1e999", True), ("true", True, True), ("null", None, True),
    ("[]", [], False), ("{}", {}, True), ("huge 1e308", 1e308, False), ("huge 2**64", 2**64, False),
    ("-1", -1, False), ("1.5", 1.5, False), ("'x'*200", "x" * 200, False),
]


def _leaves(doc: Any, path: tuple = ()) -> list[tuple[tuple, Any]]:
    out = []
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for k, v in items:
        out.append((path + (k,), v))
        out += _leaves(v, path + (k,))
    return out


def _label(path: tuple) -> str:
    s = ""
    for k in path:
        s += f"[{k}]" if isinstance(k, int) else (f".{k}" if s else str(k))
    return s


def _field_names(path: tuple) -> tuple[str, ...]:
    """Words that name the place of ``path``: its keys."""
    return tuple(str(k) for k in path if not isinstance(k, int))  # (a check on the whole list names the list)


def _set(doc: Any, path: tuple, value: Any, delete: bool = False) -> Any:
    import copy
    d = copy.deepcopy(doc)
    c = d
    for k in path[:-1]:
        c = c[k]
    if delete:
        del c[path[-1]]
    else:
        c[path[-1]] = value
    return d


def _structured_cases(fmt: Format, data: bytes) -> list[Case]:
    if fmt.kind == "json":
        doc, render = json.loads(data), lambda d: json.dumps(d, indent=1).encode()
    else:
        doc, render = tomllib.loads(data.decode()), toml_bytes
    cases = []
    top = tuple(str(k) for k in doc) if isinstance(doc, dict) else ()  # a check of the whole table names it
    for path, old in _leaves(doc):
        where, names = _label(path), _field_names(path) + top
        number = isinstance(old, (int, float)) and not isinstance(old, bool)
        for label, new, invalid in SWAPS:
            if new is None and fmt.kind == "toml":
                continue  # TOML has no null
            if type(new) is type(old) and not isinstance(new, (int, float)):
                continue
            documented = new is None and path[-1] in fmt.nullable
            cases.append(Case(fmt.name, f"swap {where} -> {label}", render(_set(doc, path, new)),
                              must_reject=number and invalid and not documented, names=names))
        cases.append(Case(fmt.name, f"delete {where}", render(_set(doc, path, None, delete=True)), False, names))
        deep: Any = old
        for _ in range(DEEP):
            deep = [deep]
        cases.append(Case(fmt.name, f"nest {where} {DEEP} deep", render(_set(doc, path, deep)), True,
                          names + ("deep", "depth", "nest")))
    return cases


def _csv_cases(fmt: Format, data: bytes) -> list[Case]:
    lines = data.decode().splitlines(keepends=True)
    header = lines[0].rstrip("\n").split(",")
    cases = []
    for row in (1, len(lines) // 2, len(lines) - 1):
        cells = lines[row].rstrip("\n").split(",")
        for col, name in enumerate(header):
            for label, new in (("'NaN'", "NaN"), ("'abc'", "abc"), ("''", ""), ("'1e999'", "1e999"), ("'inf'", "inf")):
                c = list(cells)
                c[col] = new
                mutated = lines[:row] + [",".join(c) + "\n"] + lines[row + 1:]
                cases.append(Case(fmt.name, f"row {row + 1} column {name} -> {label}", "".join(mutated).encode(),
                                  must_reject=name != "car", names=(name, "row")))
        short = lines[:row] + [",".join(cells[:-2]) + "\n"] + lines[row + 1:]
        cases.append(Case(fmt.name, f"row {row + 1} missing 2 cells", "".join(short).encode(), True, ("row",)))
    for col, name in enumerate(header):
        drop = lambda ln: ",".join(x for i, x in enumerate(ln.rstrip("\n").split(",")) if i != col) + "\n"  # noqa: E731
        cases.append(Case(fmt.name, f"delete column {name}", "".join(drop(ln) for ln in lines).encode(), True, (name,)))
    return cases


def _capture_cases(fmt: Format, data: bytes) -> list[Case]:
    lines = data.decode().splitlines(keepends=True)
    cases = []
    for row in (0, len(lines) // 2, len(lines) - 1):
        t, direction, hexdata = lines[row].split()
        for label, line in (("time 'abc'", f"abc {direction} {hexdata}"), ("time 'nan'", f"nan {direction} {hexdata}"),
                            ("direction 'xx'", f"{t} xx {hexdata}"), ("odd hex", f"{t} {direction} {hexdata[:-1]}"),
                            ("hex 'zz'", f"{t} {direction} zz{hexdata[2:]}"), ("no data", f"{t} {direction}")):
            mutated = lines[:row] + [line + "\n"] + lines[row + 1:]
            cases.append(Case(fmt.name, f"line {row + 1} {label}", "".join(mutated).encode(), True, ("line",)))
    return cases


def _byte_cases(fmt: Format, data: bytes, offsets: int, rng: random.Random) -> list[Case]:
    """Truncation at many byte offsets; re-encodings; flipped bytes (recordings)."""
    n = len(data)
    cut_at = sorted({0, 1, n // 2, n - 1, *(rng.randrange(1, n) for _ in range(offsets))})
    text = fmt.kind != "binary"
    cases = []
    for k in cut_at:
        tail = data[k:]
        # Cut text whose rest is whitespace only is the same file; TOML/CSV/captures cut at a line end can be valid.
        if text and not tail.strip():
            continue
        reject = fmt.kind == "json" or fmt.kind == "binary"
        # A recording's reader says what is readable before the damage (recording.integrity), not a byte.
        names = ("byte", "truncat", "missing", "cut") + (("damage", "corrupt", "too small") if not text else ())
        cases.append(Case(fmt.name, f"truncate at byte {k} of {n}", data[:k], reject, names))
    if text:
        cases.append(Case(fmt.name, "UTF-16 encoded", data.decode().encode("utf-16"), True, ("UTF-8", "byte", "decode")))
        cases.append(Case(fmt.name, "Latin-1 byte 0xE9 at the start", b"\xe9" + data, True, ("UTF-8", "byte", "decode")))
        k = rng.randrange(1, n)
        cases.append(Case(fmt.name, f"NUL byte at {k}", data[:k] + b"\x00" + data[k:], False, ("byte", "line", "row")))
    else:
        for k in sorted({4, *(rng.randrange(8, n - 8) for _ in range(max(4, offsets // 4)))}):
            flipped = data[:k] + bytes(b ^ 0xFF for b in data[k:k + 16]) + data[k + 16:]
            cases.append(Case(fmt.name, f"16 bytes flipped at {k}", flipped, False, ("damaged", "corrupt", "truncat", "byte")))
    return cases


def _roster_cases(fmt: Format, data: bytes) -> list[Case]:
    """What a roster cannot hold: duplicates across cars, too few or too many cars, unknown planners,
    keys or car files, a start slot beyond the grid."""
    doc = tomllib.loads(data.decode())
    cars = doc["car"]

    def case(label: str, new_cars: list, names: tuple[str, ...]) -> Case:
        return Case(fmt.name, label, toml_bytes({"car": new_cars}), True, names)

    def edit(i: int, **fields) -> list:
        return [dict(c, **fields) if k == i else dict(c) for k, c in enumerate(cars)]

    seven = [dict(c) for c in cars] + [{"name": f"extra{k}", "planner": "mpc"} for k in range(3)]
    return [
        case("duplicate name", edit(1, name=cars[0]["name"]), ("name",)),
        case("duplicate marker_id", edit(1, marker_id=cars[0]["marker_id"]), ("marker_id",)),
        case("duplicate radio_id", edit(1, radio_id=cars[0]["radio_id"]), ("radio_id",)),
        case("duplicate start_slot", edit(1, start_slot=cars[0]["start_slot"]), ("start_slot",)),
        case("start_slot beyond the grid", edit(2, start_slot=len(cars)), ("start_slot",)),
        case("unknown planner", edit(3, planner="truck"), ("planner",)),
        case("unknown key", edit(2, colour="red"), ("colour",)),
        case("car file that does not exist", edit(1, car_params="no_such_car"), ("car_params",)),
        case("7 cars", seven, ("car", "cars")),
        case("1 car", [dict(cars[0])], ("car", "cars")),
    ]


def _flag_cases(fmt: Format, data: bytes) -> list[Case]:
    """Hand-written bad values of a roster flag (the empty --cars is no roster: the two-car race)."""
    values = {"--cars": [("unknown planner", "rd3g,truck", True, ("planner",)),
                         ("7 cars", "rd3g," + ",".join(["mpc"] * 6), True, ("cars",)),
                         ("1 car", "rd3g", True, ("cars",)),
                         ("empty entry", "rd3g,,mpc", True, ("planner",)),
                         ("upper case", "RD3G,mpc", True, ("planner",)),
                         ("semicolons", "rd3g;mpc", True, ("planner",)),
                         ("non-ASCII", "rd3g,mp\u00e7", True, ("planner",)),
                         ("1000 cars", ",".join(["mpc"] * 1000), True, ("cars",)),
                         ("empty", "", False, ())],
              "--grid": [("unknown grid", "zigzag", True, ("grid", "choice")),
                         ("upper case", "RANDOM", True, ("grid", "choice")),
                         ("empty", "", True, ("grid", "choice"))]}[fmt.flag]
    return [Case(fmt.name, f"{fmt.flag} {label}: {value[:40]!r}", value.encode(), reject, names)
            for label, value, reject, names in values]


def cases_for(fmt: Format, data: bytes, offsets: int, rng: random.Random) -> list[Case]:
    if fmt.kind == "flag":  # a value on the command line: no bytes to cut
        return _flag_cases(fmt, data)
    cases = _byte_cases(fmt, data, offsets, rng)
    if fmt.name == "roster":
        cases += _roster_cases(fmt, data)
    if fmt.kind in ("json", "toml"):
        cases += _structured_cases(fmt, data)
    elif fmt.kind == "csv":
        cases += _csv_cases(fmt, data)
    elif fmt.kind == "capture":
        cases += _capture_cases(fmt, data)
    return cases


# --------------------------------------------------------------------------- judging one case
def judge(fmt: Format, case: Case, code, out: str, err: str, infile: Path, outdir: Path) -> tuple[str, str]:
    """("rejected" | "accepted", "") or ("failure", why)."""
    left = sorted(p.name for p in outdir.iterdir() if not p.name.startswith(".std"))
    if "Traceback" in err or "Traceback" in out:
        return "failure", "traceback: " + err.strip().splitlines()[-1][:300]
    if code == 2:
        message = err.strip()
        if not message:
            return "failure", "exit 2 with nothing on stderr"
        if (fmt.flag or infile.name) not in message:
            return "failure", f"message does not name the {'flag' if fmt.flag else 'file'}: {message[:300]}"
        # A mutation that cannot be valid must be caught by the loader, at its place. Another one may load and
        # then fail on its values (a marker moved so that the camera fit fails): naming the file is enough.
        if case.must_reject and not (WORDS.search(message) or any(n.lower() in message.lower() for n in case.names)):
            return "failure", f"message names no field, row or byte: {message[:300]}"
        if left:
            return "failure", f"exit 2 but output left behind: {left}"
        return "rejected", ""
    if code in fmt.accepted_codes:
        if case.must_reject:
            return "failure", f"accepted (exit {code}) though this mutation cannot be valid"
        for p in outdir.glob("*.json"):
            try:
                json.loads(p.read_bytes())
            except ValueError as exc:
                return "failure", f"accepted, but {p.name} is not complete JSON: {exc}"
        return "accepted", ""
    return "failure", f"exit {code}: {err.strip()[-300:]}"


def run_case(case: Case, seeds: Seeds, case_dir: Path) -> tuple[str, str]:
    """Write the case's file into case_dir, run its command, judge; the folder is removed unless it failed."""
    fmt = FORMATS[case.format]
    outdir = case_dir / "out"
    outdir.mkdir(parents=True, exist_ok=True)
    infile = case_dir / f"input{fmt.suffix}"
    infile.write_bytes(case.data)
    code, out, err = run_cli(fmt.argv(infile, outdir, seeds), outdir, fmt.timeout_s)
    outcome, why = judge(fmt, case, code, out, err, infile, outdir)
    if outcome == "failure":
        argv = " ".join(str(a) for a in fmt.argv(infile, outdir, seeds))
        return outcome, f"{why} (reproduce: python -m app {argv})"
    for p in sorted(case_dir.rglob("*"), reverse=True):
        p.unlink() if p.is_file() else p.rmdir()
    case_dir.rmdir()
    return outcome, why


def run(formats: list[str], per_format: int, seed: int, workdir: Path, offsets: int = 40,
        progress: Callable[[str], None] | None = None) -> dict:
    """Run up to ``per_format`` cases of each format (a seeded sample when there are more)."""
    rng = random.Random(seed)
    seeds = make_seeds(workdir / "seeds")
    report: dict = {"formats": {}, "failures": []}
    for name in formats:
        cases = cases_for(FORMATS[name], seeds.files[name], offsets, rng)
        if per_format and len(cases) > per_format:
            cases = rng.sample(cases, per_format)
        counts = {"cases": 0, "rejected": 0, "accepted": 0, "failure": 0, "seconds": 0.0}
        t0 = time.perf_counter()
        for i, case in enumerate(cases):
            outcome, why = run_case(case, seeds, workdir / name / str(i))
            counts["cases"] += 1
            counts[outcome] += 1
            if outcome == "failure":
                report["failures"].append({"format": name, "mutation": case.mutation, "why": why})
            if progress:
                progress(f"{name} {i + 1}/{len(cases)} {outcome} {case.mutation}" + (f": {why}" if why else ""))
        counts["seconds"] = time.perf_counter() - t0
        report["formats"][name] = counts
    return report


def markdown(report: dict, command: str, load: tuple[float, float]) -> str:
    lines = [f"`{command}` (1-min load average {load[0]:.1f} at the start, {load[1]:.1f} at the end; 2 cores)", "",
             "| format (command) | cases | rejected (exit 2, message naming the file) | accepted | failures | time (s) |",
             "|---|---|---|---|---|---|"]
    for name, c in report["formats"].items():
        cmd = FORMATS[name].argv(Path("F"), Path("O"), Seeds(Path(".")))[0]
        lines.append(f"| {name} (`{cmd}`) | {c['cases']} | {c['rejected']} | {c['accepted']} | {c['failure']} | {c['seconds']:.0f} |")
    for f in report["failures"][:20]:
        lines.append(f"\nfailure: {f['format']}, {f['mutation']}: {f['why']}")
    return "\n".join(lines) + "\n"


def command(args) -> int:
    """`python -m app bench malformed` (its options are in app/commands/bench.py, which imports this module only
    when the command runs: it needs hypothesis, an optional extra)."""
    names = list(FORMATS) if args.formats == "all" else args.formats.split(",")
    unknown = [n for n in names if n not in FORMATS]
    if unknown:
        raise ValueError(f"--formats: unknown format(s) {', '.join(unknown)}; known: {', '.join(FORMATS)}")
    build_parser()  # once, in the parent: every forked child starts with the commands imported
    workdir = Path(args.workdir or tempfile.mkdtemp(prefix="rd3g-malformed-"))
    load0 = os.getloadavg()[0]
    report = run(names, args.per_format, args.seed, workdir, args.offsets,
                 progress=(lambda s: print(s, flush=True)) if args.verbose else None)
    md = markdown(report, "python -m app " + " ".join(sys.argv[1:]), (load0, os.getloadavg()[0]))
    print(md)
    if args.json:
        atomic_write_text(args.json, json.dumps(report, indent=1) + "\n", stream=True)
    return 1 if report["failures"] else 0


if __name__ == "__main__":  # the old entry point, forwarded
    raise SystemExit(cli_main(["bench", "malformed", *sys.argv[1:]]))
