"""Fleet races (issue 29): the roster, the grid of rows of two, the N-car referee, the planners against
several cars, and a short simulated race of three cars with every car's result."""
import itertools
import math

import numpy as np
import pytest

from app.cli import main
from planning import MPCOpponent, RacingPlanner
from planning.frenet import frenet_separation
from race.planning import interacting_cars, make_planner
from race.referee import Referee
from race.roster import RosterCar, RosterError, RosterFileError, load_roster, make_roster, parse_cars
from race.setup import RaceSetup, RaceSetupError, RaceSpec, grid_frenet, grid_slots, start_states
from sim.collision import footprint_corners, rectangle_gap
from sim.race import SimEvent


# ---------------------------------------------------------------- roster
def test_cars_flag_names_planner_plus_position_and_defaults_by_planner():
    cars = parse_cars("rd3g,mpc,mpc,pursuit")
    assert [c.name for c in cars] == ["rd3g1", "mpc2", "mpc3", "pursuit4"]
    assert [c.planner for c in cars] == ["rd3g", "mpc", "mpc", "pursuit"]
    assert [c.marker_id for c in cars] == [0, 1, 2, 3] and [c.radio_id for c in cars] == [0, 1, 2, 3]
    assert [c.start_slot for c in cars] == [0, 1, 2, 3]
    assert [c.top_speed_mps for c in cars] == [2.0, 1.8, 1.8, 1.8]  # RaceSetup's two-car defaults by planner


@pytest.mark.parametrize("text, car, field", [
    ("rd3g,mpcc", "2", "planner"),          # unknown planner: the car's position
    ("rd3g", "-", "cars"),                  # fewer than 2
    ("rd3g,mpc,mpc,mpc,mpc,mpc,mpc", "-", "cars"),  # more than 6
])
def test_cars_flag_errors_name_car_and_field(text, car, field):
    with pytest.raises(RosterError) as err:
        parse_cars(text)
    assert (err.value.car, err.value.field) == (car, field)


@pytest.mark.parametrize("change, field", [
    ({"name": "a"}, "name"), ({"marker_id": 0}, "marker_id"), ({"radio_id": 0}, "radio_id"),
    ({"start_slot": 0}, "start_slot"), ({"top_speed_mps": -1.0}, "top_speed_mps"), ({"start_slot": 5}, "start_slot"),
])
def test_roster_duplicates_and_bad_values_name_the_second_car(change, field):
    a = RosterCar("a", "rd3g", marker_id=0, radio_id=0, start_slot=0)
    b = RosterCar(**{**dict(name="b", planner="mpc", marker_id=1, radio_id=1, start_slot=1), **change})
    with pytest.raises(RosterError) as err:
        make_roster([a, b])
    assert err.value.field == field and err.value.car in ("a", "b")


def test_roster_file_loads_and_rejects_unknown_keys_and_wrong_types(tmp_path):
    good = tmp_path / "lab.toml"
    good.write_text('[[car]]\nname = "red"\nplanner = "rd3g"\nmarker_id = 7\nradio_id = 3\n'
                    '[[car]]\nname = "blue"\nplanner = "mpc"\ntop_speed_mps = 1.5\nstart_slot = 0\n'
                    '[[car]]\nname = "green"\nplanner = "human"\nstart_slot = 1\n')
    cars = load_roster(good)
    assert [(c.name, c.marker_id, c.radio_id, c.start_slot) for c in cars] == [
        ("red", 7, 3, 2), ("blue", 0, 0, 0), ("green", 1, 1, 1)]  # unset ids: the smallest free ones
    assert cars[1].top_speed_mps == 1.5
    for body, where in (('[[car]]\nname = "a"\nplanner = "rd3g"\ncolour = 1\n[[car]]\nname = "b"\nplanner = "mpc"\n',
                         "car[0].colour"),
                        ('[[car]]\nname = "a"\nplanner = "rd3g"\n[[car]]\nname = "b"\nplanner = "mpc"\nmarker_id = "1"\n',
                         "car[1].marker_id"),
                        ('[[car]]\nname = "a"\nplanner = "rd3g"\n[[car]]\nname = "a"\nplanner = "mpc"\n', "car a: name")):
        bad = tmp_path / "bad.toml"
        bad.write_text(body)
        with pytest.raises(RosterFileError) as err:
            load_roster(bad)
        assert str(bad) in str(err.value) and where in str(err.value)


def test_cli_rejects_a_bad_roster_with_exit_code_2(tmp_path, capsys):
    out = tmp_path / "race.rrd"
    assert main(["race", "--cars", "rd3g,mpc,kart", "--out", str(out)]) == 2
    assert "car 3: planner" in capsys.readouterr().err
    assert main(["race", "--cars", "rd3g", "--out", str(out)]) == 2
    assert main(["race", "--cars", "rd3g,human", "--out", str(out)]) == 2  # no person in a simulation
    assert "car human2: planner" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text('[[car]]\nname = "a"\nplanner = "rd3g"\nradio_id = 9\n[[car]]\nname = "b"\nplanner = "mpc"\nradio_id = 9\n')
    assert main(["race", "--roster", str(bad), "--out", str(out)]) == 2
    assert f"--roster: {bad}: car b: radio_id" in capsys.readouterr().err
    assert main(["batch", "--cars", "rd3g,rd3g,mpc", "--races", "1"]) == 2  # one RD3G car against its counterfactual
    assert "2 RD3G cars" in capsys.readouterr().err
    assert not out.exists()


def test_two_car_setup_is_the_roster_of_rd3g_and_opponent(track, car):
    setup = RaceSetup(track=track, car=car, opponent="pursuit", rd3g_top_speed_mps=1.9, opponent_top_speed_mps=1.7)
    assert [(c.name, c.planner, c.top_speed_mps) for c in setup.cars] == [("rd3g", "rd3g", 1.9),
                                                                            ("opponent", "pursuit", 1.7)]
    with pytest.raises(RaceSetupError):
        RaceSetup(track=track, car=car, roster=parse_cars("rd3g,mpc,mpc"))  # three cars need a grid


# ---------------------------------------------------------------- grid
def _grid(track, car, cars, grid="roster", seed=3, jitter=0.0):
    return RaceSetup(track=track, car=car, seed=seed, roster=parse_cars(cars), grid=grid, finish="all",
                     grid_jitter_m=jitter)


def test_grid_is_rows_of_two_about_one_car_length_apart(track, car):
    setup = _grid(track, car, "rd3g,mpc,mpc,mpc,pursuit,pursuit")
    s, ey = grid_frenet(setup)
    L, length = track.length, car.geometry.footprint_length_m
    ahead = np.array([math.remainder(si - s[0], L) for si in s])  # along the track from slot 0
    # slots 0/1 row 0, 2/3 row 1, 4/5 row 2; left (+ey) for even slots; no jitter: exact lanes and rows
    assert np.allclose(ey, [0.15, -0.15] * 3)
    assert ahead[1] == pytest.approx(0.0, abs=1e-9)
    gap = -ahead[2]
    assert 1.9 * length <= gap <= 2.1 * length  # about one car length of free space between rows
    assert np.allclose(ahead, [0, 0, -gap, -gap, -2 * gap, -2 * gap])
    assert setup.start_s_m[0] <= s[0] <= setup.start_s_m[1]
    # on the straight (the oval's turns begin after s = 0.45 m): the closest footprints are a car and the
    # car behind it, the row gap minus a car length apart; a row's two cars are 0.3 m minus a car width apart
    x0 = start_states(setup)
    corners = footprint_corners(x0[:, 0], x0[:, 1], x0[:, 2], length, car.geometry.footprint_width_m,
                                car.geometry.footprint_offset_m)
    gaps = [float(rectangle_gap(corners[i:i + 1], corners[j:j + 1])[0]) for i, j in itertools.combinations(range(6), 2)]
    assert np.all(track.curvature(s) == 0)
    assert min(gaps) == pytest.approx(gap - length, abs=1e-6)
    assert gaps[0] == pytest.approx(0.3 - car.geometry.footprint_width_m, abs=1e-6)  # pair (0, 1)


def test_jittered_and_random_grids_keep_the_slots(track, car):
    roster = _grid(track, car, "rd3g,mpc,mpc,mpc", jitter=0.01)
    s, ey = grid_frenet(roster)
    assert np.all(np.abs(np.abs(ey) - 0.15) <= 0.01 + 1e-12)
    shuffled = [_grid(track, car, "rd3g,mpc,mpc,mpc", grid="random", seed=seed) for seed in range(6)]
    slots = [tuple(grid_slots(g)) for g in shuffled]
    assert all(sorted(sl) == [0, 1, 2, 3] for sl in slots) and len(set(slots)) > 1  # a permutation, seeded
    assert slots[0] == tuple(grid_slots(_grid(track, car, "rd3g,mpc,mpc,mpc", grid="random", seed=0)))


# ---------------------------------------------------------------- referee
def test_referee_judges_collisions_per_pair_off_track_and_finishing_order(track, car):
    ref = Referee(track, car, ("a", "b", "c"), laps_to_win=1)
    s0 = np.array([0.5, 0.3, 0.1])                 # a leads, c last, just after the line (a lap to go)
    xs, ys, hs = track.to_cartesian(s0, np.zeros(3), np.zeros(3))
    states = np.column_stack([xs, ys, hs, np.zeros((3, 3))])
    ref.observe(0.0, states)
    # c runs into a's back: c has a ahead along its heading, a has c behind -> c at fault
    entry = ref.sim_event(SimEvent(time=1.0, kind="collision", car=0, other=2), states)
    assert entry == ("collision", "a with c (fault c)")
    ref.sim_event(SimEvent(time=1.5, kind="off_track", car=1), states)
    assert [(c.cars, c.at_fault) for c in ref.collisions] == [(("a", "c"), "c")]
    # every car drives a lap; b crosses the line first, then c, a does not finish
    L = track.length
    for t, s in ((1.6, [3.6, 3.3, 3.0]), (1.8, [6.6, 6.3, 6.0]), (2.0, [L - 0.6, L - 0.2, L - 0.4]),
                 (3.0, [L - 0.3, 0.3, 0.05])):  # b crosses s = 0 at 2.4 s, c at 2.89 s, a not yet
        xs, ys, hs = track.to_cartesian(np.array(s), np.zeros(3), np.zeros(3))
        ref.observe(t, np.column_stack([xs, ys, hs, np.zeros((3, 3))]))
    assert ref.finish_order == ["b", "c"] and not ref.all_finished
    results = {r.name: r for r in ref.results(ref.finish_order, ref.lap_times_s)}
    assert (results["b"].finish_position, results["c"].finish_position, results["a"].finish_position) == (1, 2, None)
    assert (results["c"].at_fault_collisions, results["a"].at_fault_collisions) == (1, 0)
    assert results["b"].off_track == 1 and results["a"].lap_times_s == []
    # closest: 0.2 m centre to centre on the straight, minus a car length
    assert ref.min_gap_m == pytest.approx(0.2 - car.geometry.footprint_length_m, abs=1e-6)
    assert results["b"].lap_times_s == [pytest.approx(2.4)] and results["c"].lap_times_s == [pytest.approx(2.0 + 0.4 / 0.45)]


# ---------------------------------------------------------------- planners against several cars
def test_interacting_cars_are_within_reach_of_the_horizon_nearest_first():
    # 10 m lap, reach = max(top) * 1 s + 0.2 m: 2.2 m for 2 m/s
    progress = [0.0, 1.0, -2.1, 5.0, 9.5]
    assert interacting_cars(0, progress, [2.0, 1.8, 1.8, 1.8, 1.8], 1.0, 0.2, 10.0) == [4, 1, 2]
    # car 3 alone (none within 2.2 m): the nearest, car 2 at 2.9 m round the lap (car 1 is 4 m away)
    assert interacting_cars(3, progress, [2.0] * 5, 1.0, 0.2, 10.0) == [2]


@pytest.mark.parametrize("cls", [MPCOpponent, RacingPlanner])
def test_only_the_car_that_starts_too_close_is_relaxed(cls, monkeypatch):
    """Us at s = 1 m, one car 13 cm away (inside the collision distance), one 1.5 m ahead: the close
    car's distance is relaxed below the current separation, the far car keeps the nominal one (MPC: as
    an obstacle; RD3G: as a player, with us and with the close car)."""
    setup = RaceSpec().load()
    planner = make_planner(cls, setup, 1.8, **({"opponent_top_speed_mps": 1.8} if cls is RacingPlanner else {}))
    seen = {}
    original = cls._finish

    def capture(self, problem, d, ey, *args):
        seen["problem"] = problem
        return original(self, problem, d, ey, *args)

    monkeypatch.setattr(cls, "_finish", capture)
    me, close, far = np.array([1.0, 0.0, 1.0, 0.0]), np.array([1.12, 0.05, 1.0, 0.0]), np.array([2.5, 0.0, 1.0, 0.0])
    planner.plan(me, np.array([close, far]))
    nominal = planner.tm.collision_distance()
    problem = seen["problem"]
    if cls is MPCOpponent:
        d_close, d_far = (np.atleast_1d(o.min_distance) for o in problem.obstacles)
        d_others = []
    else:
        d = problem.collision.pair_min_distances(3, planner.config.horizon)
        d_close, d_far, d_others = d[0, 1], d[0, 2], d[1, 2]
    # relaxed at k = 1 below the current separation, measured as the constraint does
    scale = planner.tm.along_track_scale([me[0], close[0], far[0]], [me[1], close[1], far[1]])
    assert d_close[0] < float(frenet_separation(*(close - me)[:2], scale)) < nominal
    assert np.allclose(d_far, nominal) and np.allclose(d_others, nominal)


def test_follow_cap_and_defence_take_the_strictest_other_car(track, car):
    setup = RaceSpec().load()
    p = make_planner(RacingPlanner, setup, 2.0, opponent_top_speed_mps=1.8)
    me = np.array([1.0, 0.0, 1.5, 0.0])
    a, b = np.array([1.15, 0.0, 1.2, 0.0]), np.array([1.2, 0.0, 0.8, 0.0])
    both = p.follow_speed_cap(me, np.array([a, b]), [True, True])
    assert both == pytest.approx(min(p.follow_speed_cap(me, a, True), p.follow_speed_cap(me, b, True)))
    assert p.follow_speed_cap(me, np.array([a, b]), [True, False]) == pytest.approx(p.follow_speed_cap(me, a, True))


# ---------------------------------------------------------------- a short fleet race
def test_three_car_race_finishes_with_every_cars_result():
    from race.simulation import run_race

    setup = RaceSpec(roster=parse_cars("rd3g,mpc,pursuit"), seed=1).load()
    assert setup.grid == "roster" and setup.finish == "all"
    s = run_race(setup).summary()
    assert sorted(s["finishing_order"]) == ["mpc2", "pursuit3", "rd3g1"]  # every car finished
    assert s["winner"] == s["finishing_order"][0]
    cars = {c["name"]: c for c in s["cars"]}
    assert [c["name"] for c in s["cars"]] == ["rd3g1", "mpc2", "pursuit3"]  # roster order
    assert sorted(c["finish_position"] for c in s["cars"]) == [1, 2, 3]
    for c in s["cars"]:
        assert len(c["lap_times_s"]) == 1 and 3.0 < c["lap_times_s"][0] < 15.0
        assert c["off_track"] == s["off_track"][c["name"]]
    assert cars["rd3g1"]["solve_ms_p50"] > 0 and cars["mpc2"]["solve_ms_p99"] > 0
    assert cars["pursuit3"]["solve_ms_p50"] is None and cars["pursuit3"]["planner"] == "pursuit"
    assert s["rd3g_at_fault"] == cars["rd3g1"]["at_fault_collisions"]
    assert len(s["collision_events"]) == s["collisions"]
    for c in s["collision_events"]:
        assert set(c["cars"]) <= set(cars) and c["at_fault"] in c["cars"]


# ---------------------------------------------------------------- fleet batch
def test_fleet_batch_pairs_positions_by_seed():
    from app.fleet_batch import fleet_roster, summarise_fleet

    roster = parse_cars("rd3g,mpc,mpc,mpc")
    swapped = fleet_roster(roster, "counterfactual")
    assert [c.planner for c in swapped] == ["mpc"] * 4 and swapped[0].name == "rd3g1"
    assert swapped[0].top_speed_mps == 2.0 and swapped[1:] == roster[1:]   # everything else equal

    def rec(arm, seed, position, unfinished=False, at_fault=0):
        return {"cell": ("fleet", arm), "seed": seed, "cars": 4, "position": position, "unfinished": unfinished,
                "at_fault": at_fault, "collisions": at_fault}

    records = [rec("rd3g", 0, 1), rec("counterfactual", 0, 2), rec("rd3g", 1, 2, at_fault=1),
               rec("counterfactual", 1, 2), rec("rd3g", 2, None, unfinished=True), rec("counterfactual", 2, 3)]
    f = summarise_fleet(records)
    # positions 1, 2, 4 (unfinished = last of 4) against 2, 2, 3: differences -1, 0, +1
    assert f["races"] == 3 and f["rd3g_mean_position"] == pytest.approx(7 / 3)
    assert f["counterfactual_mean_position"] == pytest.approx(7 / 3)
    assert f["paired_difference"]["mean"] == pytest.approx(0.0)
    half = 4.302652729911275 * 1.0 / math.sqrt(3)  # t(0.975, 2 dof) from a table, sample sd of (-1, 0, 1) = 1
    assert f["paired_difference"]["ci95"] == pytest.approx([-half, half])
    assert f["rd3g_win_rate"] == pytest.approx(1 / 3) and f["counterfactual_win_rate"] == 0.0
    assert f["rd3g_at_fault"] == 1 and f["unfinished"] == 1
