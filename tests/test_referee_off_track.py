"""Progress made off the track does not count (sim.race.LapBookkeeper, docs/racing.md "Off track"), in
every mode: hand-built arc-length trajectories with the expected laps worked by hand, the hardware
referee judging the track limits from the cars' states, and the review of a recording with an excursion
giving the simulator's own laps."""
from __future__ import annotations

import json

import numpy as np
import pytest

from sim.race import LapBookkeeper

L = 10.0          # lap (m)
V = 1.0           # m/s
DT = 0.1          # samples (s)
ALLOWANCE = 0.16  # one footprint length of the buzzracer car (m)


def _drive(on_track, off_s=None, t_end=14.0, allowance=ALLOWANCE, s_after=None):
    """One car from s0 = 0.5 at V (first half of the lap: lap 1 timed from t = 0), sampled every DT.
    ``on_track(t)`` -> the footprint excess at t (linear near the limit, so the crossing is exact);
    ``off_s(t)``: where the projection puts the car deep in the excursion (not used for counting);
    ``s_after(t)``: its arc length after the excursion. Returns the bookkeeper and its events."""
    book = LapBookkeeper(L, 1, np.array([0.5]), allowance_m=allowance)
    events = []
    for k in range(0, int(round(t_end / DT)) + 1):
        t = k * DT
        e = on_track(t)
        s = 0.5 + V * t
        if s_after is not None and s_after(t) is not None:
            s = s_after(t)
        elif off_s is not None and e > 0.02:  # deep in the excursion: whatever the projection says
            s = off_s(t)
        events += book.update(t, np.array([s]), np.array([e]))
    return book, events


def _excursion(t_leave, t_rejoin):
    """Footprint excess rising from 0 at t_leave and back to 0 at t_rejoin at 0.2 m/s (a triangle)."""
    mid = 0.5 * (t_leave + t_rejoin)
    return lambda t: 0.2 * (t - t_leave) if t < mid else 0.2 * (t_rejoin - t)


def test_a_cut_is_not_counted_and_the_car_drives_it_again():
    # Leaves at t = 2.05 s (s = 2.55 m), cuts to s = 6.0 m where it rejoins at t = 3.05 s and drives on
    # at 1 m/s. Gain 3.45 m, of which the allowance 0.16 m counts: 3.29 m not counted. Counted at the
    # rejoin: 2.55 + 0.16 = 2.71 m; the line (10 m) is 7.29 m further: t = 3.05 + 7.29 = 10.34 s.
    book, events = _drive(_excursion(2.05, 3.05), off_s=lambda t: 8.0 if int(t * 10) % 2 else 1.0,
                          s_after=lambda t: 6.0 + V * (t - 3.05) if t > 2.6 else None)
    laps = [e for e in events if e.kind == "lap"]
    assert len(laps) == 1 and laps[0].time == pytest.approx(10.34, abs=1e-9)
    assert book.lap_times[0] == [pytest.approx(10.34, abs=1e-9)]
    cut = [e for e in events if e.kind == "not_counted"]
    assert len(cut) == 1 and cut[0].car == 0
    assert (cut[0].left_s_m, cut[0].rejoined_s_m, cut[0].not_counted_m) == (
        pytest.approx(2.55, abs=1e-9), pytest.approx(6.0, abs=1e-9), pytest.approx(3.29, abs=1e-9))
    assert [e.kind for e in events if e.kind in ("off_track", "on_track")] == ["off_track", "on_track"]
    assert list(book.off_track_count) == [1] and book.not_counted[0] == pytest.approx(3.29, abs=1e-9)
    # Without the track limits the same positions give the cut lap: the line at s = 10 m at t = 7.05 s.
    free = LapBookkeeper(L, 1, np.array([0.5]))
    t = np.arange(0, 141) * DT
    s = np.where(t > 2.6, 6.0 + V * (t - 3.05), 0.5 + V * t)
    assert [e.time for k in range(141) for e in free.update(t[k], s[k:k + 1]) if e.kind == "lap"] == [
        pytest.approx(7.05, abs=1e-9)]


def test_an_excursion_within_the_allowance_keeps_its_lap():
    # Off for 0.1 s (0.1 m gained, below the allowance): the lap is the one without the excursion,
    # (10 - 0.5) / 1 = 9.5 s; nothing is taken off.
    book, events = _drive(_excursion(2.05, 2.15))
    assert book.lap_times[0] == [pytest.approx(9.5, abs=1e-9)]
    assert not [e for e in events if e.kind == "not_counted"] and list(book.off_track_count) == [1]
    # Off for 0.3 s (0.3 m): 0.3 - 0.16 = 0.14 m not counted, the lap 0.14 s longer.
    book, events = _drive(_excursion(2.05, 2.35))
    assert book.lap_times[0] == [pytest.approx(9.64, abs=1e-9)]
    assert [e.not_counted_m for e in events if e.kind == "not_counted"] == [pytest.approx(0.14, abs=1e-9)]


def test_rejoining_behind_costs_nothing_extra_and_a_cut_over_the_line_completes_no_lap():
    # Leaves at s = 2.55 m (t = 2.05 s), rejoins 0.55 m behind (s = 2.0 m at t = 3.05 s): the line is
    # 8 m ahead of where it rejoined, t = 11.05 s.
    book, events = _drive(_excursion(2.05, 3.05), s_after=lambda t: 2.0 + V * (t - 3.05) if t > 2.6 else None)
    assert book.lap_times[0] == [pytest.approx(11.05, abs=1e-9)] and book.not_counted[0] == 0.0
    # Leaves at s = 9.55 m (t = 9.05 s), cuts over the line to s = 1.0 m (t = 9.55 s): gain 1.45 m, 1.29 m
    # not counted; counted 9.55 + 0.16 = 9.71 m at the rejoin, the line 0.29 m later: t = 9.84 s.
    book, events = _drive(_excursion(9.05, 9.55), s_after=lambda t: 1.0 + V * (t - 9.55) if t > 9.3 else None)
    assert [e.time for e in events if e.kind == "lap"] == [pytest.approx(9.84, abs=1e-9)]
    assert book.not_counted[0] == pytest.approx(1.29, abs=1e-9)


def test_a_car_that_never_comes_back_completes_no_lap():
    # Off the track from t = 2.05 s to the end, "driving" a whole lap outside (seed 19's mpc3).
    book, events = _drive(lambda t: 0.2 * (t - 2.05), off_s=lambda t: (0.5 + 2 * V * t) % L, t_end=20.0)
    assert book.lap_times[0] == [] and int(book.laps[0]) == 0 and bool(book.off_track[0])


def test_backing_over_the_line_does_not_restart_the_first_lap():
    # Starts at s = 0.2 m (lap 1 timed from t = 0), backs over the line to s = 9.8 m and drives on: the
    # lap ends when it crosses the line again after a whole lap, timed from the start.
    book = LapBookkeeper(L, 1, np.array([0.2]))
    s = [0.1, 9.9, 9.8, 9.9, 0.1] + [0.1 + 0.5 * k for k in range(1, 21)]
    events = [e for k, sk in enumerate(s) for e in book.update(0.1 * (k + 1), np.array([sk]))]
    # back over the line at 0.15 s, forward again at 0.45 s; s = 10.1 m (0.1 m past the line) at 2.5 s
    assert [e.time for e in events if e.kind == "lap"] == [pytest.approx(2.48, abs=1e-9)]
    assert book.lap_times[0] == [pytest.approx(2.48, abs=1e-9)]


def test_the_hardware_referee_judges_the_track_limits_from_the_states():
    """On hardware the referee counts laps and excursions from the perceived states with the same rule:
    a car that drives beside the oval's bottom straight, 0.5 m outside, completes no lap until it has
    driven the distance again."""
    from race.referee import Referee
    from tracks import load_track
    from vehicles.params import load_car_params

    track, car = load_track("oval"), load_car_params("buzzracer")
    g = car.geometry
    ref = Referee(track, car, ("a", "b"), laps_to_win=1)
    length = track.length
    half = 0.5 * 0.6
    # Car a: along the lap at 1 m/s from s = 0.2 m, sampled every 0.05 s; at samples 5-13 (s = 0.45-0.85 m,
    # the bottom straight) it is 0.5 m to the right of the centre line (off). Car b: 0.3 m ahead of it on
    # the centre line.
    k = np.arange(0, 241)
    t, s = 0.05 * k, 0.2 + 0.05 * k
    ey_a = np.where((k >= 5) & (k <= 13), -0.5, 0.0)
    entries = []
    for i in k:
        xa, ya, ha = track.to_cartesian(s[i] % length, ey_a[i], 0.0)
        xb, yb, hb = track.to_cartesian((s[i] + 0.3) % length, 0.0, 0.0)
        states = np.array([[xa, ya, ha, 1, 0, 0], [xb, yb, hb, 1, 0, 0]], dtype=float)
        entries += [ref.log_entry(e) for e in ref.observe(float(t[i]), states)]
    assert ref.off_track == {"a": 1, "b": 0}
    # The right corners cross the edge (|ey| = half width of the track) where the car's centre is at
    # |ey| = 0.3 - w/2 of the 0.5 m sideways jump between two samples (the excess is linear in ey on the
    # straight): at a fraction (0.3 - w/2) / 0.5 of the step from s = 0.4 to 0.45 m; they come back at the
    # same fraction before the end of the step from s = 0.85 to 0.9 m.
    f = (half - 0.5 * g.footprint_width_m) / 0.5
    left, rejoined = 0.4 + f * 0.05, 0.9 - f * 0.05
    lost = rejoined - left - g.footprint_length_m
    text = [e[1] for e in entries if e is not None and e[0] == "not_counted"]
    assert text == [f"a left at s = {left:.2f} m, rejoined at s = {rejoined:.2f} m: {lost:.2f} m not counted"]
    assert ref.not_counted_m["a"] == pytest.approx(lost, abs=1e-6)
    # b (from s = 0.5 m) crosses the line at t = L - 0.5 s; a at counted s = L: true s = L + lost,
    # t = L - 0.2 + lost
    laps = ref.lap_times_s
    assert laps["b"] == [pytest.approx(length - 0.5, abs=1e-6)]
    assert laps["a"] == [pytest.approx(length - 0.2 + lost, abs=1e-6)]
    assert ref.finish_order == ["b", "a"]
    results = {r.name: r for r in ref.results(ref.finish_order, laps, 1)}
    assert results["a"].off_track == 1 and results["a"].not_counted_m == pytest.approx(lost, abs=1e-6)


def test_review_of_a_recording_with_an_excursion_gives_the_races_laps(tmp_path):
    """A car on the oval cuts the first turn through the infield (pure pursuit 0.6 m inside from s = 1
    to 3 m) in the simulator (track checks every 5 ms); its 30 Hz recording reviewed: the simulator's
    own lap, to the interpolation between the recording's samples."""
    from planning.pursuit import PurePursuitController
    from race.recording import RaceRecorder, record_car
    from race.referee import Referee
    from sim import Simulator
    from test_loop_support import run_cli
    from tracks import load_track
    from vehicles.params import load_car_params

    track, car = load_track("oval"), load_car_params("buzzracer")

    def race(cut_m, path=None):
        sim = Simulator(track, [car], laps_to_win=1)
        x, y = track.position(0.3)
        sim.reset([[float(x), float(y), float(track.heading(0.3)), 0, 0, 0]])
        driver = PurePursuitController(track, car, target_speed_mps=1.5)
        rec = None
        if path is not None:
            rec = RaceRecorder(path, recording_id="cut", background=False, car_names=("rd3g",), realtime=False)
            rec.static_document("race/setup", json.dumps({"mode": "simulation", "track": "oval", "laps": 1}))
        referee = Referee(track, car, ("rd3g",))
        dt, k = 1 / 30, 0
        while sim.race_status().winner is None and sim.time < 15.0:
            state = sim.state(0)
            s = float(track.to_frenet(state[0], state[1])[0])
            driver.lateral_offset_m = cut_m if 1.0 < s < 3.0 and sim.time < 4.0 else 0.0  # the first time round
            if rec is not None:
                record_car(rec, k, sim.time, "rd3g", state, car.geometry)
            for ev in sim.step([driver.command(state, dt)], dt):
                entry = referee.sim_event(ev, sim.states)
                if rec is not None and entry is not None:
                    rec.event(ev.time, *entry)
            k += 1
        if rec is not None:
            state = sim.state(0)
            record_car(rec, k, sim.time, "rd3g", state, car.geometry)
            rec.close()
        return sim.race_status()

    clean = race(0.0)
    assert clean.off_track_count == (0,)
    path = tmp_path / "cut.rrd"
    cut = race(0.6, path)
    assert cut.off_track_count == (1,) and cut.not_counted_m[0] > 0.5
    # The distance not counted is driven again at about the cruising speed: the lap is longer than the
    # clean one, though the infield path is shorter.
    assert cut.lap_times[0][0] > clean.lap_times[0][0] + 0.5 * cut.not_counted_m[0] / 1.5
    js = tmp_path / "cut.json"
    assert run_cli(["review", str(path), "--json", str(js), "--no-plots"]) == 0
    s = json.loads(js.read_text())
    assert s["lap_times_s"] == {"rd3g": [pytest.approx(cut.lap_times[0][0], abs=2e-3)]}
    texts = [e["text"] for e in s["events"] if e["kind"] == "not_counted"]
    assert len(texts) == 1 and texts[0].startswith("rd3g left at s = ") and texts[0].endswith(" m not counted")
    assert float(texts[0].split(": ")[1].split()[0]) == pytest.approx(cut.not_counted_m[0], abs=0.006)
