"""Rerun telemetry of a race: a buffered writer for the real-time loop and a reader for reviews.

Writer (:class:`RaceRecorder`, the one writer of every race mode): rows are collected per entity and
sent as columns with ``send_columns`` (one call per entity instead of one ``log`` per value, which
costs 60-200 us each on this machine). In real time (``background=True``) the loop thread only
appends rows to a queue (about a microsecond per value) and a background thread sends them every
``flush_every_s``; the simulated race (``background=False``) collects them in its own thread and
sends them every ``flush_every_rows`` rows and at ``close``. Events and camera images are logged as
they come (rare). Every row carries two timelines: ``sim_time`` (race time, s) and ``control_step``
(loop tick or control step). With a live view (``live``, recording.live) the same recording also goes
to Rerun viewers as it is written, and the simulated race sends its rows every ``flush_every_s`` too.

Reader (:func:`load_recording`): Rerun's own chunk reader (``rerun.chunk.RrdReader``, rerun 0.41)
streams the chunks of the first recording in the file; each entity's rows are concatenated and
sorted by ``sim_time``. Entity paths: docs/racing.md (simulated race) and docs/race-stack.md.
"""
from __future__ import annotations

import ast
import dataclasses
import json
import math
import queue
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from fileio import check_output_path
from planning.frenet import EY, S
from race.config import lower_realtime_priority
from race.roster import PLANNERS, two_car_roster
from recording.blueprint import race_blueprint  # the top-level package recording/, not this module
from recording.integrity import read_verified
from recording.live import LiveView
from sim.collision import footprint_corners

APPLICATION_ID = "rd3g_race"
EVENTS_ENTITY = "race/events"
SETUP_ENTITY = "race/setup"
LIVE_FLUSH_TIMEOUT_S = 10.0  # at close, how long the live viewers may take to receive the rest of a race
# Each car's colour by its place in the roster (recordings and review plots): red, blue, green, orange,
# purple, brown.
CAR_PALETTE = ((230, 60, 40), (40, 110, 230), (40, 160, 70), (240, 150, 20), (150, 70, 190), (140, 90, 50))


def car_colors(names: Sequence[str]) -> dict[str, tuple[int, int, int]]:
    """{car name: (r, g, b)} in roster order (CAR_PALETTE, repeated past six cars)."""
    return {name: CAR_PALETTE[i % len(CAR_PALETTE)] for i, name in enumerate(names)}


class RecordingError(ValueError):
    """A recording file is missing, unreadable or lacks what a review needs."""


# --------------------------------------------------------------------------- writer
class RaceRecorder:
    """Buffered rerun recording of one race (one .rrd file) of the cars ``car_names``; see the module
    doc for the two modes. The file opens in the viewer on the race layout (recording.blueprint):
    the real-time one (camera, estimates, loop timing) unless ``realtime=False`` (simulated race)."""

    def __init__(self, path, recording_id: str, flush_every_s: float = 0.5, background: bool = True,
                 flush_every_rows: int = 20000, car_names: Sequence[str] = (), realtime: bool = True,
                 live: LiveView | None = None) -> None:
        import rerun as rr  # here, not at the top: the reader's users (sysid) need not load the SDK's writer

        self.rr = rr
        self.path = Path(path)
        self.realtime = realtime  # loop timing is recorded (race.loop_recording)
        check_output_path(self.path)  # a regular file (a link to one) or new; Rerun writes it as the race goes
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id)
        blueprint = race_blueprint(car_names, realtime=realtime)
        self.live = live
        self.live_error: str | None = None  # why the live sinks could not be flushed at close (the file is whole)
        if live is None:
            self.rec.save(str(self.path), default_blueprint=blueprint)
        else:  # one recording, the file and the viewers (recording.live)
            self.rec.set_sinks(rr.FileSink(str(self.path)), *live.sinks(), default_blueprint=blueprint)
        self.flush_every_s = float(flush_every_s)
        self.flush_every_rows = int(flush_every_rows)
        self._rows: dict[tuple[str, str], list] = defaultdict(list)
        self._pending_rows = 0
        self._closed = False
        self.rows_written = 0
        self._thread = None
        self._next_flush = time.monotonic() + self.flush_every_s
        if background:
            self._queue: queue.SimpleQueue = queue.SimpleQueue()
            self._put = self._queue.put
            self._thread = threading.Thread(target=self._run, name="RaceRecorder", daemon=True)
            self._thread.start()
        else:  # a live view also gets the rows every flush_every_s, not only every flush_every_rows
            self._put = self._handle_now if live is None else self._handle_now_live

    # ---- called from the loop (cheap: queue puts in the background mode)
    def scalar(self, entity: str, step: int, t: float, value: float) -> None:
        self._put(("scalars", entity, step, t, float(value)))

    def points(self, entity: str, step: int, t: float, xy) -> None:
        self._put(("points", entity, step, t, np.asarray(xy, dtype=np.float32).reshape(-1, 2)))

    def strip(self, entity: str, step: int, t: float, xy) -> None:
        self.strips(entity, step, t, [xy])

    def strips(self, entity: str, step: int, t: float, xys) -> None:
        """Several line strips in one row (e.g. a planner's predictions of every other car)."""
        self._put(("strips", entity, step, t, [np.asarray(xy, dtype=np.float32).reshape(-1, 2) for xy in xys]))

    def event(self, t: float, kind: str, text: str, step: int | None = None) -> None:
        self._put(("event", EVENTS_ENTITY, step, t, f"{kind}: {text}"))

    def image(self, entity: str, step: int, t: float, image: np.ndarray) -> None:
        self._put(("image", entity, step, t, image))

    # ---- static content (called before the race, from the loop thread)
    def static_track(self, track) -> None:
        rr = self.rr
        left, right = track.boundaries(0.02)
        centre = track.position(np.linspace(0, track.length, 400))
        self.rec.log("world/track/left", rr.LineStrips2D([np.vstack([left, left[:1]])]), static=True)
        self.rec.log("world/track/right", rr.LineStrips2D([np.vstack([right, right[:1]])]), static=True)
        self.rec.log("world/track/centre", rr.LineStrips2D([centre], colors=[[120, 120, 120]]), static=True)

    def static_racing_line(self, track, line, entity: str = "world/track/racing_line") -> None:
        """The racing line (tracks.racing_line.RacingLine) as a closed strip of short pieces, each
        coloured by the speed profile: blue at the line's slowest speed to red at its fastest."""
        x, y = track.to_cartesian(line.s, line.ey)
        points = np.column_stack([x, y])
        pieces = np.stack([points, np.roll(points, -1, axis=0)], axis=1)
        v = line.speed_mps
        share = (v - v.min()) / max(float(v.max() - v.min()), 1e-9)
        colors = np.column_stack([255 * share, 60 * np.ones_like(share), 255 * (1 - share)]).astype(np.uint8)
        self.rec.log(entity, self.rr.LineStrips2D(list(pieces), colors=colors), static=True)

    def static_document(self, entity: str, text: str) -> None:
        self.rec.log(entity, self.rr.TextDocument(text), static=True)

    def static_color(self, entity: str, kind: str, rgb) -> None:
        archetype = {"points": self.rr.Points2D, "strips": self.rr.LineStrips2D}[kind]
        self.rec.log(entity, archetype.from_fields(colors=[list(rgb)]), static=True)

    def static_car_colors(self, names: Sequence[str]) -> None:
        """Each car's colour (car_colors, roster order) on its position, footprint and plan, its
        predictions of the other cars in grey."""
        for name, rgb in car_colors(names).items():
            for entity, kind in (("position", "points"), ("footprint", "strips"), ("plan", "strips")):
                self.static_color(f"world/cars/{name}/{entity}", kind, rgb)
            self.static_color(f"world/cars/{name}/predicted_other", "strips", (150, 150, 150))

    def close(self) -> None:
        """Flush everything and finish the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout=30.0)
        else:
            self._flush()
        if self.live is None:
            self.rec.flush()
        else:
            try:
                self.rec.flush(timeout_sec=LIVE_FLUSH_TIMEOUT_S)
            except RuntimeError as exc:  # a viewer gone or never reached: its copy is cut short, not the file
                self.live_error = str(exc)
        self.rec.disconnect()  # finishes the file (footer/manifest)

    # ---- background thread
    def _run(self) -> None:
        # Under --rt-priority: below the loop, but still real-time - a time-shared thread that is
        # preempted while holding the GIL would stall the loop (priority inversion).
        lower_realtime_priority(10)
        next_flush = time.monotonic() + self.flush_every_s
        while True:
            try:
                item = self._queue.get(timeout=max(0.0, next_flush - time.monotonic()))
            except queue.Empty:
                item = ()
            if item is None:
                self._flush()
                return
            if item:
                self._handle(item)
            if time.monotonic() >= next_flush:
                self._flush()
                next_flush = time.monotonic() + self.flush_every_s

    def _handle(self, item) -> None:
        kind, entity, step, t, payload = item
        if kind == "event":
            self._log_now(entity, step, t, self.rr.TextLog(payload))
        elif kind == "image":
            self._log_now(entity, step, t, self.rr.Image(payload))
        else:
            self._rows[(kind, entity)].append((step, t, payload))
            self._pending_rows += 1

    def _handle_now(self, item) -> None:
        """Synchronous mode: collect in the caller's thread, send every flush_every_rows rows."""
        self._handle(item)
        if self._pending_rows >= self.flush_every_rows:
            self._flush()

    def _handle_now_live(self, item) -> None:
        """Synchronous mode with a live view: also send every flush_every_s of wall time."""
        self._handle(item)
        if self._pending_rows >= self.flush_every_rows or time.monotonic() >= self._next_flush:
            self._flush()
            self._next_flush = time.monotonic() + self.flush_every_s

    def _log_now(self, entity, step, t, archetype) -> None:
        rec = self.rec
        if step is not None:
            rec.set_time("control_step", sequence=int(step))
        rec.set_time("sim_time", duration=float(t))
        rec.log(entity, archetype)

    def _flush(self) -> None:
        rr = self.rr
        rows, self._rows = self._rows, defaultdict(list)
        self._pending_rows = 0
        for (kind, entity), items in rows.items():
            steps = np.array([r[0] for r in items], dtype=np.int64)
            times = np.array([r[1] for r in items], dtype=float)
            indexes = [rr.TimeColumn("control_step", sequence=steps), rr.TimeColumn("sim_time", duration=times)]
            if kind == "scalars":
                columns = rr.Scalars.columns(scalars=np.array([r[2] for r in items]))
            elif kind == "points":
                columns = rr.Points2D.columns(positions=np.concatenate([r[2] for r in items])).partition(
                    [len(r[2]) for r in items])
            else:
                columns = rr.LineStrips2D.columns(strips=[s for r in items for s in r[2]]).partition(
                    [len(r[2]) for r in items])
            self.rec.send_columns(entity, indexes=indexes, columns=columns)
            self.rows_written += len(items)


def record_car(rec: RaceRecorder, step: int, t: float, name: str, state, geometry) -> None:
    """One car's pose rows (every mode): ``world/cars/{name}/position``, ``footprint`` (closed rectangle
    of the car file's geometry) and ``cars/{name}/speed_mps``; state [x, y, heading, vx, vy, ...]."""
    corners = footprint_corners(state[0], state[1], state[2], geometry.footprint_length_m,
                                geometry.footprint_width_m, geometry.footprint_offset_m)
    rec.points(f"world/cars/{name}/position", step, t, state[:2])
    rec.strip(f"world/cars/{name}/footprint", step, t, np.vstack([corners, corners[:1]]))
    rec.scalar(f"cars/{name}/speed_mps", step, t, math.hypot(state[3], state[4]))


def record_plan(rec: RaceRecorder, step: int, t: float, track, name: str, plan, solve_ms: float) -> None:
    """One plan's rows (every mode): the car's planned trajectory and its predictions of the other cars
    it planned with (world frame, one strip each), the first planned control, the planning wall time
    (ms) and the solver iterations."""
    xy = [np.column_stack(track.to_cartesian(plan.x[row, :, S], plan.x[row, :, EY])) for row in range(len(plan.x))]
    rec.strip(f"world/cars/{name}/plan", step, t, xy[0])
    rec.strips(f"world/cars/{name}/predicted_other", step, t, xy[1:])
    rec.scalar(f"cars/{name}/planned/accel_mps2", step, t, plan.u[0, 0])
    rec.scalar(f"cars/{name}/planned/delta_rad", step, t, plan.u[0, 1])
    rec.scalar(f"planner/{name}/solve_ms", step, t, solve_ms)
    rec.scalar(f"planner/{name}/iterations", step, t, plan.iterations)


# --------------------------------------------------------------------------- reader
@dataclass
class EntityRows:
    """All rows of one entity: timelines (sim_time in s, control_step) and the data columns."""

    sim_time: np.ndarray = field(default_factory=lambda: np.zeros(0))
    control_step: np.ndarray | None = None
    columns: dict[str, list] = field(default_factory=dict)  # component name -> per-row python values


@dataclass
class RecordingData:
    path: Path
    application_id: str
    recording_id: str
    entities: dict[str, EntityRows]
    static: dict[str, dict[str, list]]

    def has(self, entity: str) -> bool:
        return entity in self.entities

    def scalars(self, entity: str) -> tuple[np.ndarray, np.ndarray]:
        """(sim_time s, values) of a Scalars entity; empty arrays if it is absent."""
        rows = self.entities.get(entity)
        if rows is None or "Scalars:scalars" not in rows.columns:
            return np.zeros(0), np.zeros(0)
        values = np.array([v[0] if v else np.nan for v in rows.columns["Scalars:scalars"]], dtype=float)
        return rows.sim_time, values

    def points(self, entity: str) -> tuple[np.ndarray, list[np.ndarray]]:
        rows = self.entities.get(entity)
        if rows is None or "Points2D:positions" not in rows.columns:
            return np.zeros(0), []
        return rows.sim_time, [np.asarray(v, dtype=float).reshape(-1, 2) for v in rows.columns["Points2D:positions"]]

    def strips(self, entity: str) -> tuple[np.ndarray, list[list[np.ndarray]]]:
        rows = self.entities.get(entity)
        if rows is None or "LineStrips2D:strips" not in rows.columns:
            return np.zeros(0), []
        return rows.sim_time, [[np.asarray(s, dtype=float).reshape(-1, 2) for s in v]
                               for v in rows.columns["LineStrips2D:strips"]]

    def texts(self, entity: str) -> tuple[np.ndarray, list[str]]:
        rows = self.entities.get(entity)
        if rows is None or "TextLog:text" not in rows.columns:
            return np.zeros(0), []
        return rows.sim_time, [v[0] if v else "" for v in rows.columns["TextLog:text"]]

    def document(self, entity: str) -> str | None:
        values = self.static.get(entity, {}).get("TextDocument:text")
        return values[-1][0] if values else None

    def setup(self) -> dict:
        """The race setup document as a dict (JSON, or the Python repr the simulated race writes)."""
        text = self.document(SETUP_ENTITY)
        if text is None:
            return {}
        try:
            return json.loads(text)
        except json.JSONDecodeError:
            try:
                value = ast.literal_eval(text)
            except (ValueError, SyntaxError):
                return {}
            return value if isinstance(value, dict) else {}

    def roster(self) -> list[dict]:
        """The recorded race's cars in roster order, each {"name", "marker_id", "planner", ...}: the
        simulated race's ``roster``, the real-time race's ``cars`` with their ``planners``; a recording
        made before rosters were recorded has the two-car roster of its ``opponent``."""
        setup = self.setup()
        entries = setup.get("roster") or setup.get("cars") or []
        cars = [dict(e) for e in entries if isinstance(e, dict) and isinstance(e.get("name"), str)]
        planners = setup.get("planners") if isinstance(setup.get("planners"), dict) else {}
        opponent = setup.get("opponent") if setup.get("opponent") in PLANNERS else "mpc"
        two_car = {c.name: dataclasses.asdict(c) for c in two_car_roster(opponent, 1.0, 1.0)}
        if not cars:
            return list(two_car.values())
        for c in cars:
            c.setdefault("planner", planners.get(c["name"], two_car.get(c["name"], {}).get("planner")))
        return cars


def load_recording(path) -> RecordingData:
    """Read a race recording with rerun's chunk reader. Raises RecordingError naming the file, and
    saying what is readable if the file is truncated or corrupt (recording.integrity)."""
    import pyarrow as pa  # with rerun, loaded when a recording is read (see RaceRecorder.__init__)

    path = Path(path)
    try:
        store, chunks = read_verified(path)  # truncated or corrupt files: RecordingDamage (a ValueError)
    except FileNotFoundError:
        raise RecordingError(f"{path}: recording not found") from None
    except ValueError as exc:
        raise RecordingError(str(exc)) from None
    parts: dict[str, list] = defaultdict(list)
    static: dict[str, dict[str, list]] = defaultdict(dict)
    for chunk in chunks:
        batch = chunk.to_record_batch()
        entity = chunk.entity_path.lstrip("/")
        data_names = [f.name for f in batch.schema
                      if f.name not in ("control_step", "sim_time", "log_time") and not f.name.startswith("rerun.")]
        if chunk.is_static:
            for name in data_names:
                static[entity][name] = batch.column(name).to_pylist()
            continue
        if "sim_time" not in batch.schema.names:
            continue
        t = batch.column("sim_time").cast(pa.int64()).to_numpy(zero_copy_only=False) * 1e-9
        step = (batch.column("control_step").to_numpy(zero_copy_only=False)
                if "control_step" in batch.schema.names else np.full(len(t), -1))
        cols = {name: batch.column(name).to_pylist() for name in data_names if not name.startswith("Image:")}
        parts[entity].append((t, step, cols))
    entities = {}
    for entity, items in parts.items():
        t = np.concatenate([p[0] for p in items])
        step = np.concatenate([p[1] for p in items])
        names = set().union(*(p[2].keys() for p in items))
        cols = {n: sum((p[2].get(n, [None] * len(p[0])) for p in items), []) for n in names}
        order = np.lexsort((step, t))
        entities[entity] = EntityRows(t[order], step[order], {n: [v[i] for i in order] for n, v in cols.items()})
    return RecordingData(path, store.application_id, store.recording_id, entities, dict(static))
