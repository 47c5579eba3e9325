"""`python -m app check --hil`: the pre-race check against the emulated hardware passes on a correct
set-up and fails, naming the car and the fault, on faulty ones (set up in the HIL world with --hil-fault).
Four check runs of ~10 s each: the correct set-up, two runs with two independent faults each, and four cars
with two radio ids swapped."""
from __future__ import annotations

import math

import pytest

from app.cli import main
from tracking.checks import Displacement, displacement, judge_throttle_pulse


def run_check(capsys, *extra) -> tuple[int, list[str]]:
    # 15 frames/s: a quarter of the default 60's rendering load, so that a host whose cores are shared with other
    # work still renders every frame (at 30 frames/s a load average of 12 on 2 cores delivered 21.6)
    code = main(["check", "--hil", "--link-protocol", "buzzracer-fhss", "--fps", "15", *extra])
    lines = capsys.readouterr().out.splitlines()
    return code, lines


def item(lines, name):
    hits = [l for l in lines if l.startswith(("[PASS] ", "[FAIL] ")) and l[7:].startswith(name + ":")]
    assert len(hits) == 1, f"{name}: {lines}"
    return hits[0]


def test_correct_setup_passes(capsys):
    code, lines = run_check(capsys)
    assert code == 0, "\n".join(lines)
    for name in ("camera", "fixed markers", "marker rd3g", "marker opponent", "serial", "steering rd3g",
                 "radio rd3g", "steering opponent", "radio opponent", "failsafe"):
        assert item(lines, name).startswith("[PASS]")
    assert "9/9 seen" in item(lines, "fixed markers")
    assert "check: 10/10 passed" in lines[-1]


def test_swapped_radio_ids_and_a_covered_fixed_marker(capsys):
    code, lines = run_check(capsys, "--hil-fault", "swapped_radio_ids", "--hil-fault", "covered_fixed_marker:44")
    assert code == 1
    fixed = item(lines, "fixed markers")
    assert fixed.startswith("[FAIL]") and "fixed marker(s) 44 not seen" in fixed
    for car, other in (("rd3g", "opponent"), ("opponent", "rd3g")):
        radio = item(lines, f"radio {car}")
        assert radio.startswith("[FAIL]") and f"{other} moved" in radio and "radio ids swapped" in radio
        assert item(lines, f"steering {car}").startswith("[PASS]")  # zero throttle: nothing rolls


def test_reversed_throttle_and_a_missing_car_marker(capsys):
    code, lines = run_check(capsys, "--hil-fault", "reversed_throttle:opponent", "--hil-fault", "missing_marker:rd3g")
    assert code == 1
    assert item(lines, "marker rd3g").startswith("[FAIL]") and "marker 0 not seen" in item(lines, "marker rd3g")
    assert "not checked" in item(lines, "radio rd3g")
    radio = item(lines, "radio opponent")
    assert radio.startswith("[FAIL]") and "moved backwards: throttle channel reversed" in radio
    assert item(lines, "marker opponent").startswith("[PASS]")


def test_displacement_in_the_car_frame():
    # a car heading 90 deg (along +y) that moved to +y by 3 cm and to -x by 1 cm: 3 cm forward, 1 cm left
    d = displacement((1.0, 2.0, math.pi / 2), (0.99, 2.03, math.pi / 2))
    assert d.along_m == pytest.approx(0.03) and d.across_m == pytest.approx(0.01)
    assert d.distance_m == pytest.approx(math.hypot(0.03, 0.01))


@pytest.mark.parametrize("moves, ok, says", [
    ({"a": Displacement(0.04, 0.0, 0.04), "b": Displacement(0, 0, 0.001)}, True, "a moved +4.0 cm"),
    ({"a": Displacement(-0.04, 0.0, 0.04), "b": Displacement(0, 0, 0.0)}, False, "throttle channel reversed"),
    ({"a": Displacement(0.0, 0.0, 0.0), "b": Displacement(0.04, 0, 0.04)}, False, "radio ids swapped"),
    ({"a": Displacement(0.04, 0.0, 0.04), "b": Displacement(0.04, 0, 0.04)}, False, "b moved 4.0 cm too"),
    ({"a": Displacement(0.001, 0.0, 0.001), "b": Displacement(0, 0, 0)}, False, "did not move"),
    ({"a": Displacement(0.01, 0.04, 0.041), "b": Displacement(0, 0, 0)}, False, "sideways"),
])
def test_throttle_pulse_verdicts(moves, ok, says):
    verdict, text = judge_throttle_pulse("a", moves)
    assert verdict is ok and says in text


def test_two_swapped_radio_ids_among_four_cars(capsys):
    """A fleet roster: each car's radio is checked in turn; the two swapped ones fail naming each other."""
    code, lines = run_check(capsys, "--cars", "rd3g,mpc,mpc,mpc", "--hil-fault", "swapped_radio_ids")
    assert code == 1
    for car, other in (("rd3g1", "mpc2"), ("mpc2", "rd3g1")):
        radio = item(lines, f"radio {car}")
        assert radio.startswith("[FAIL]") and f"{other} moved" in radio and "radio ids swapped" in radio
    for car in ("mpc3", "mpc4"):
        assert item(lines, f"radio {car}").startswith("[PASS]")
        assert item(lines, f"marker {car}").startswith("[PASS]")
