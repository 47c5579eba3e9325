"""The two speed models of the paper's two-car experiment (race.setup.SPEED_MODELS, docs/racing.md):
the option on `race` and `batch`, the set-up a preference race builds (hand-checked numbers: the
authors' speed references 1.0 + 0.1 i m/s, one hard top speed), and a short preference race."""
import argparse
import json
import math

import numpy as np
import pytest

from app.cli import UserError
from app.commands import batch as batch_cmd
from app.commands import race as race_cmd
from planning.frenet import EY, S, V
from race.planning import RacePlanners
from race.roster import RosterCar, RosterError, make_roster
from race.setup import RaceSpec, start_states
from race.simulation import run_race


def _parser():
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    race_cmd.register(sub)
    batch_cmd.register(sub)
    return parser


@pytest.mark.parametrize("command", ["race", "batch"])
def test_speed_model_option_parses_and_bad_values_exit_2(command, capsys):
    p = _parser()
    assert p.parse_args([command]).speed_model == "limits"
    assert p.parse_args([command, "--speed-model", "preference"]).speed_model == "preference"
    with pytest.raises(SystemExit) as exc:
        p.parse_args([command, "--speed-model", "soft"])
    assert exc.value.code == 2
    assert "--speed-model" in capsys.readouterr().err


def test_preference_race_has_one_hard_limit_and_two_reference_speeds(track, car):
    """RD3G given the higher top speed (the batch's fast cell): both cars' hard limit 2.0 m/s, speed
    references 1.1 (RD3G) and 1.0 m/s (MPC), each car starting at its reference speed."""
    setup = RaceSpec(speed_model="preference", start="rear", rd3g_top_speed_mps=2.0, opponent_top_speed_mps=1.6).load()
    rd3g, opp = setup.cars
    assert (rd3g.top_speed_mps, opp.top_speed_mps) == (2.0, 2.0)
    assert (rd3g.reference_speed_mps, opp.reference_speed_mps) == (1.1, 1.0)
    x0 = start_states(setup)
    np.testing.assert_allclose(x0[:, 3], [1.1, 1.0])   # vx along the heading
    np.testing.assert_allclose(x0[:, 4:], 0.0)
    # About one car length of free space: centre to centre 1.75-2.25 car lengths (0.16 m) along the track.
    d = float(np.hypot(*(x0[0, :2] - x0[1, :2])))
    assert 1.75 * 0.16 - 0.02 < d < 2.25 * 0.16 + 0.02
    # The planners: identical hard speed bound, the reference in the cost (state order s, ey, v, epsi).
    planners = RacePlanners(setup)
    for name, ref in (("rd3g", 1.1), ("opponent", 1.0)):
        cfg = planners.models[name].config
        assert (cfg.top_speed_mps, cfg.reference_speed_mps) == (2.0, ref)
        cost = planners.models[name]._cost(2.0, cfg.reference_speed_mps)
        assert cost.x_ref[V] == pytest.approx(ref)
        assert cost.x_ref[EY] == cfg.raceline_ey_m and cost.x_ref[S] == 0.0
    # The reference never exceeds the plan's speed bound (e.g. a cornering cap of 0.9 m/s).
    assert planners.models["rd3g"]._cost(0.9, 1.1).x_ref[V] == pytest.approx(0.9)
    assert planners.refs == [1.1, 1.0] and planners.tops == [2.0, 2.0]


def test_preference_slow_cell_swaps_the_references_not_the_limits():
    setup = RaceSpec(speed_model="preference", start="front", rd3g_top_speed_mps=1.6, opponent_top_speed_mps=2.0).load()
    rd3g, opp = setup.cars
    assert (rd3g.top_speed_mps, opp.top_speed_mps) == (2.0, 2.0)
    assert (rd3g.reference_speed_mps, opp.reference_speed_mps) == (1.0, 1.1)
    np.testing.assert_allclose(start_states(setup)[:, 3], [1.0, 1.1])


def test_limits_model_is_unchanged():
    """The default: different hard top speeds, the cost's reference = the top speed, standing start."""
    setup = RaceSpec(rd3g_top_speed_mps=2.0, opponent_top_speed_mps=1.6).load()
    assert [(c.top_speed_mps, c.reference_speed_mps, c.start_speed_mps) for c in setup.cars] == [(2.0, None, 0.0),
                                                                                                  (1.6, None, 0.0)]
    np.testing.assert_allclose(start_states(setup)[:, 3:], 0.0)
    planners = RacePlanners(setup)
    assert planners.models["opponent"]._cost(1.6, None).x_ref[V] == 1.6


def test_bad_speed_model_and_fleet_preference_name_the_field():
    from race.setup import RaceSetupError

    with pytest.raises(RaceSetupError, match="speed_model: must be one of limits, preference"):
        RaceSpec(speed_model="soft").load()
    with pytest.raises(RaceSetupError, match="speed_model: preference is the two-car"):
        RaceSpec(speed_model="preference", roster=make_roster([RosterCar("a", "rd3g"), RosterCar("b", "mpc")])).load()
    for field, value in (("reference_speed_mps", 0.0), ("reference_speed_mps", math.nan), ("start_speed_mps", -1.0)):
        with pytest.raises(RosterError, match=f"car a: {field}"):
            make_roster([RosterCar("a", "rd3g", **{field: value}), RosterCar("b", "mpc")])


def test_batch_preference_rejects_slow_speed():
    args = _parser().parse_args(["batch", "--speed-model", "preference", "--slow-speed", "1.5", "--races", "1"])
    with pytest.raises(UserError, match="--slow-speed"):
        batch_cmd.run(args)


def test_short_preference_race_finishes(track, car):
    """One lap, RD3G behind with the higher reference: the race finishes without contact, and neither
    car ever exceeds the shared hard top speed (2.0 m/s; 2 % for the simulator's tracking of the bound)."""
    setup = RaceSpec(speed_model="preference", start="rear", seed=1, rd3g_top_speed_mps=2.0,
                     opponent_top_speed_mps=1.6).load()
    o = run_race(setup)
    assert o.winner in ("rd3g", "opponent")
    assert o.collisions == []
    speed = np.hypot(o.trace_states[..., 3], o.trace_states[..., 4])
    assert speed.max() <= 2.0 * 1.02


def test_batch_json_names_the_speed_model(tmp_path):
    out = tmp_path / "b.json"
    args = _parser().parse_args(["batch", "--speed-model", "preference", "--races", "1", "--max-time", "0.3",
                                 "--json", str(out)])
    assert batch_cmd.run(args) == 0
    d = json.loads(out.read_text())
    assert d["speed_model"] == "preference"
    assert [(c["start"], c["speed"], c["races"]) for c in d["cells"]] == [(*cell, 1) for cell in batch_cmd.CELLS]
    z2 = 1.959964 ** 2
    for c in d["cells"]:
        # 0.3 s of race time: no winner. The Wilson interval of 0 wins in 1 race is [0, z^2 / (1 + z^2)].
        assert c["rd3g_wins"] == 0 and c["unfinished"] == 1
        assert c["win_rate_ci95"] == pytest.approx([0.0, z2 / (1 + z2)], abs=1e-6)
        assert {"win_rate", "rd3g_wins", "collisions", "unfinished", "solve_ms_p99"} <= set(c)
