"""The loop bench's winner-distribution comparison (app.realtime.bench.winner_distribution) against
hand-computed counts and the exact McNemar p-value from the binomial distribution."""
from math import comb

from app.realtime.bench import winner_distribution


def _row(sim, hil, end="finished"):
    return {"sim": {"winner": sim}, "hil": {"winner": hil, "end_reason": end}}


def test_counts_and_exact_mcnemar_p():
    # 2 seeds RD3G wins only in simulation, 4 only in HIL, 3 both, 1 neither, 1 HIL unfinished.
    rows = ([_row("rd3g", "opponent")] * 2 + [_row("opponent", "rd3g")] * 4 + [_row("rd3g", "rd3g")] * 3
            + [_row("opponent", "opponent")] + [_row("opponent", None, "held_neutral")])
    d = winner_distribution(rows)
    assert (d["sim_rd3g_wins"], d["hil_rd3g_wins"], d["sim_only"], d["hil_only"]) == (5, 7, 2, 4)
    assert d["hil_unfinished"] == 1 and d["hil_end_reasons"] == {"finished": 10, "held_neutral": 1}
    # two-sided exact test on 6 discordant pairs, 2 vs 4: 2 * P(X <= 2), X ~ Bin(6, 1/2)
    expected = 2 * sum(comb(6, k) for k in range(3)) / 2 ** 6
    assert abs(d["mcnemar_p"] - expected) < 1e-12


def test_no_discordant_pairs_means_no_evidence_of_a_difference():
    d = winner_distribution([_row("rd3g", "rd3g"), _row("opponent", "opponent")])
    assert d["mcnemar_p"] == 1.0 and d["sim_only"] == d["hil_only"] == 0


def test_pool_adds_the_runs_seed_pairs(tmp_path, capsys):
    import json

    from app.cli import main

    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps([_row("rd3g", "opponent"), _row("opponent", "rd3g")]))
    b.write_text(json.dumps([_row("opponent", "rd3g"), _row("rd3g", "rd3g")]))
    assert main(["bench", "loop", "--pool", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    # 4 pairs: simulation-only 1, HIL-only 2 -> p = 2 * P(X <= 1), X ~ Bin(3, 1/2) = 1
    assert "2 runs, 4 seed pairs: RD3G won 2 in simulation and 3 in HIL" in out
    assert "discordant seeds 1 (simulation only) : 2 (HIL only), exact McNemar p = 1" in out


def _fleet(order, planners, end="finished"):
    """A four-car `race --json` record with the roster keys: ``order`` the cars that finished."""
    cars = [{"name": name, "planner": planner, "finish_position": order.index(name) + 1 if name in order else None}
            for name, planner in planners.items()]
    return {"winner": order[0] if order else None, "finishing_order": list(order), "cars": cars, "end_reason": end}


def test_fleet_comparison_reads_the_roster():
    """Four cars named without 'rd3g': wins and positions come from each record's roster keys."""
    from app.realtime.bench import order_agreement

    planners = {"a1": "mpc", "b2": "rd3g", "c3": "rd3g", "d4": "mpc"}
    rows = [
        {"sim": _fleet(["b2", "a1", "c3", "d4"], planners), "hil": _fleet(["b2", "a1", "c3", "d4"], planners)},
        {"sim": _fleet(["c3", "a1", "b2", "d4"], planners), "hil": _fleet(["a1", "c3", "b2", "d4"], planners)},
        {"sim": _fleet(["a1", "d4", "b2", "c3"], planners), "hil": _fleet(["a1", "d4"], planners, "time_limit")},
    ]
    d = winner_distribution(rows)
    # an RD3G car (b2 or c3) won seeds 0 and 1 in simulation, seed 0 only in HIL
    assert (d["sim_rd3g_wins"], d["hil_rd3g_wins"], d["sim_only"], d["hil_only"]) == (2, 1, 1, 0)
    o = order_agreement(rows)
    assert o["same_order"] == 1 and o["same_winner"] == 2 and o["car_pairs"] == 12
    # seed 0: 4 equal; seed 1: b2, d4 equal (c3 and a1 swapped); seed 2: a1, d4 equal (b2, c3 unfinished in HIL)
    assert o["same_position"] == 8
    # |shift| over cars finished in both: seed 0: 0 x4; seed 1: 1, 1, 0, 0; seed 2: 0, 0
    assert o["position_shift_mean"] == 2 / 10


def test_records_without_roster_keys_are_the_two_car_race():
    from app.realtime.bench import finishing_order, positions, rd3g_won

    old = {"winner": "rd3g"}
    assert rd3g_won(old) and finishing_order(old) == ["rd3g"] and positions(old) == {"rd3g": 1}
    assert not rd3g_won({"winner": "opponent"}) and finishing_order({"winner": None}) == []
