"""Every race recording ships its default Rerun blueprint, and every entity path the blueprint names
is in the recording. Read back with the rerun SDK's chunk reader (not the project's reader)."""
from __future__ import annotations

from collections import defaultdict

import pytest


def _store_chunks(path, kind: str):
    import rerun as rr

    reader = rr.chunk.RrdReader(path)
    stores = reader.recordings() if kind == "recording" else reader.blueprints()
    assert len(stores) == 1, f"{path}: {len(stores)} {kind} stores"
    return stores[0], list(reader.stream(store=stores[0]))


def blueprint_views(path) -> dict[str, dict]:
    """The views of the recording's blueprint: display name -> {kind, origin, queries}."""
    store, chunks = _store_chunks(path, "blueprint")
    fields: dict[str, dict] = defaultdict(dict)
    for chunk in chunks:
        batch = chunk.to_record_batch()
        entity = chunk.entity_path.strip("/")
        for name in batch.schema.names:
            if name.startswith(("ViewBlueprint:", "ViewContents:")):
                view = entity.split("/")[1] if entity.startswith("view/") else entity
                fields[view][name.split(":")[1]] = batch.column(name).to_pylist()[-1]
    views = {}
    for f in fields.values():
        if "display_name" in f:
            views[f["display_name"][0]] = {"kind": f["class_identifier"][0], "origin": f["space_origin"][0],
                                           "queries": f.get("query", ["$origin/**"])}
    return views


def named_paths(view: dict) -> list[str]:
    """Entity paths a view names: its origin and its '+' content expressions, '$origin' resolved,
    '/**' (this entity and everything below) removed."""
    out = [view["origin"]]
    for q in view["queries"]:
        q = q.strip()
        if q.startswith("-"):
            continue
        q = q.removeprefix("+").strip().replace("$origin", view["origin"]).removesuffix("/**")
        out.append(q)
    return [p.strip("/") for p in out]


def recorded_entities(path) -> set[str]:
    _, chunks = _store_chunks(path, "recording")
    return {c.entity_path.strip("/") for c in chunks}


def assert_blueprint_matches(path, expected_views: set[str]) -> dict:
    views = blueprint_views(path)
    assert set(views) == expected_views
    entities = recorded_entities(path)
    for name, view in views.items():
        for p in named_paths(view):
            assert p == "" or any(e == p or e.startswith(p + "/") for e in entities), \
                f"view {name!r} names {p!r}, which is not in {path}"
    return views


SIMULATION_VIEWS = {"track", "trails (last 3 s)", "speeds (m/s)", "commands", "solve and loop times (ms)", "events"}


def test_simulated_race_recording_opens_on_the_race_layout(tmp_path):
    from race.setup import RaceSetup
    from race.simulation import run_race
    from tracks import load_track
    from vehicles.params import load_car_params

    path = tmp_path / "sim.rrd"
    run_race(RaceSetup(track=load_track("oval"), car=load_car_params("buzzracer"), seed=1, max_time_s=0.5),
             telemetry_path=path)
    views = assert_blueprint_matches(path, SIMULATION_VIEWS)
    assert views["track"]["kind"] == "2D" and views["events"]["kind"] == "TextLog"
    assert named_paths(views["trails (last 3 s)"])[2:] == ["world/cars/rd3g/position", "world/cars/opponent/position"]
    assert named_paths(views["speeds (m/s)"])[1:] == ["cars/rd3g/speed_mps", "cars/opponent/speed_mps"]
    assert named_paths(views["commands"])[1:] == ["cars/rd3g/command", "cars/opponent/command"]
