"""Identifiability before a claim: parameters the logs do not excite are not fitted, not claimed and not written;
the significance test needs more than one block; `other` terms are bounded."""

import math

import numpy as np
import pytest

from sim import Simulator
from sysid.data import build_trajectory
from sysid.diagnose import Fit, SysidSettings, identify, improvement, split_starts
from sysid.excitation import excitation
from sysid.generate import sim_effects
from sysid.log import DriveLog
from sysid.model import PredictionErrors
from tracks import load_track
from vehicles.params import load_car_params

CAR = load_car_params("buzzracer")


def circle(t: np.ndarray, radius=0.8, speed=1.2) -> DriveLog:
    """Constant throttle and steering on a circle (no command ever changes)."""
    angle = speed / radius * t
    steer = math.atan(CAR.geometry.wheelbase_m / radius)
    return DriveLog("<circle>", t, np.zeros(t.size, dtype=int), radius * np.cos(angle), radius * np.sin(angle),
                    np.angle(np.exp(1j * (angle + math.pi / 2))), np.full(t.size, 0.3), np.full(t.size, steer), None,
                    np.arange(2, t.size + 2))


def test_constant_commands_on_a_circle_excite_gain_and_offset_only():
    traj = build_trajectory(circle(np.arange(0, 40, 1 / 30)))
    split = split_starts(traj, 30, SysidSettings())
    exc = excitation(traj, split.train, 30, CAR)
    # No command changes: no delay, play or response to time; a steady circle: no straight driving.
    for p in ("steering_delay_s", "throttle_delay_s", "steering_backlash_rad", "extra_drag_n_per_mps2"):
        assert not exc[p].identifiable, p
    assert "0 (need >= 20)" in exc["throttle_delay_s"].reason
    assert "straight driving" in exc["extra_drag_n_per_mps2"].reason
    # 0.11 rad of steady, unsaturated steering while moving: gain and offset are excited; one side only.
    assert exc["steering_gain"].identifiable and exc["steering_offset_rad"].identifiable
    assert not exc["steering_gain_asymmetry"].identifiable
    # 1.8 m/s^2 lateral acceleration (1.2^2 / 0.8): grip is excited.
    assert exc["tire_grip_scale"].identifiable


@pytest.fixture(scope="module")
def constant_throttle_log():
    """40 s of the simulated car with a hidden 0.08 s delay on both channels, driven with a constant throttle
    and a sine on the steering: the throttle delay cannot show in these data."""
    dt, n = 1 / 30, 1200
    sim = Simulator(load_track("oval"), [CAR], effects=sim_effects({"actuation_delay": 0.08}, 0.002, 0.01), seed=3,
                    physics_dt=0.002, check_dt=0.01)
    sim.reset([[0.0, 0.0, 0.0, 0.8, 0.0, 0.0]])
    rows = []
    for i in range(n):
        steer = 0.25 * math.sin(2 * math.pi * 0.35 * i * dt) + 0.08 * math.sin(2 * math.pi * 1.3 * i * dt)
        m = sim.measure(0)
        rows.append((m.t, m.x, m.y, m.heading, 0.3, steer))
        sim.step([[0.3, steer]], dt)
    a = np.array(rows)
    return DriveLog("<constant throttle>", a[:, 0], np.zeros(n, dtype=int), a[:, 1], a[:, 2], a[:, 3], a[:, 4],
                    a[:, 5], None, np.arange(2, n + 2))


def test_no_throttle_delay_is_claimed_or_written_without_throttle_changes(constant_throttle_log):
    result = identify(build_trajectory(constant_throttle_log), CAR,
                      SysidSettings(fit_max_starts=120, heldout_max_starts=500, n_bootstrap=300))
    left_out = {p: why for n in result.not_identifiable for p, why in zip(n.params, n.reasons)}
    assert "throttle_delay_s" in left_out and "throttle command change" in left_out["throttle_delay_s"]
    assert result.car_out.corrections.throttle_delay_s == CAR.corrections.throttle_delay_s
    assert all("throttle_delay_s" not in e.params for e in result.selected)
    # The steering delay is excited (the sine) and found.
    delay = [e for e in result.selected if e.effect == "actuation_delay"]
    assert delay and delay[0].params["steering_delay_s"] == pytest.approx(0.08, rel=0.2)


def test_held_out_windows_in_one_block_are_never_significant():
    traj = build_trajectory(circle(np.arange(0, 40, 1 / 30)))
    starts = np.arange(300, 330)  # 1 s of windows: one 2 s block

    def fit(err: float) -> Fit:
        e = np.full((starts.size, 30), err)
        return Fit((), {}, {}, None, PredictionErrors(e, e, e, e, e), None)

    class S:
        heldout = starts

    reduction, confidence = improvement(traj, S, fit(0.1), fit(0.01), SysidSettings())
    assert reduction == pytest.approx(0.9) and confidence == 0.0


@pytest.fixture(scope="module")
def clean_log():
    from sysid.generate import generate_log

    return generate_log(CAR, {}, 0.6, seed=31, physics_dt=0.002)


@pytest.mark.parametrize("what", ["wheelbase", "steering_scale"])
def test_wrong_geometry_or_steering_scale_is_diagnosed_as_such(clean_log, what, recwarn):
    """A car file with a 30 % too long wheelbase, or steering commands off by 3x (a wrong normalised scale), is
    reported as a geometry/steering-scale misfit: never as drift, drag or `other`."""
    import dataclasses

    car, log, want = CAR, clean_log, None
    if what == "wheelbase":
        g = CAR.geometry
        car = dataclasses.replace(CAR, geometry=dataclasses.replace(g, lf_m=1.3 * g.lf_m, lr_m=1.3 * g.lr_m))
        want = 1.3  # the car turns 1.3 x as sharply as a 1.3 x longer car
    else:
        log = dataclasses.replace(clean_log, steering=clean_log.steering / 3.0)
        want = 3.0
    result = identify(build_trajectory(log), car, SysidSettings(fit_max_starts=120, heldout_max_starts=500,
                                                                n_bootstrap=300))
    names = {e.effect for e in result.selected}
    assert not names & {"motor_drift", "longitudinal_drag", "other"}, names
    diag = result.geometry_diagnosis
    assert diag is not None and diag["steering_gain"] == pytest.approx(want, rel=0.15)
    assert diag["equivalent_wheelbase_m"] == pytest.approx(car.geometry.wheelbase_m / want, rel=0.15)
    # Overflowing trial predictions are counted, not printed.
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


def _identify_a_car_with(**corrections):
    """A 36 s log of the BuzzRacer whose true corrections are ``corrections``, identified with the nominal file."""
    import dataclasses

    from sysid.generate import generate_log

    sim_car = dataclasses.replace(CAR, corrections=dataclasses.replace(CAR.corrections, **corrections))
    log = generate_log(sim_car, {}, 0.6, seed=41, physics_dt=0.002)
    return identify(build_trajectory(log), CAR, SysidSettings(fit_max_starts=120, heldout_max_starts=500,
                                                              n_bootstrap=300))


def test_a_wrong_throttle_map_is_named_as_such_not_as_drag_or_drift():
    """The simulated car's motor sees 0.75 x (|u| - 0.05): the throttle map is named and measured, drag and battery
    drift (which also change the speed) are not claimed."""
    result = _identify_a_car_with(throttle_gain=0.75, throttle_dead_band=0.05)
    assert [e.effect for e in result.selected] == ["throttle_map"]
    fitted = result.car_out.corrections
    assert fitted.throttle_gain == pytest.approx(0.75, rel=0.1)
    assert fitted.throttle_dead_band == pytest.approx(0.05, abs=0.015)
    assert fitted.extra_drag_n_per_mps2 == 0.0 and fitted.motor_force_drift_per_s == 0.0
    assert result.selected[0].heading_reduction >= 0 and result.selected[0].speed_reduction > 0.5


def test_the_planners_command_mapping_inverts_the_throttle_map():
    import dataclasses

    from planning.commands import CommandMapper

    car = dataclasses.replace(CAR, corrections=dataclasses.replace(CAR.corrections, throttle_gain=0.75,
                                                                   throttle_dead_band=0.05, throttle_curvature=0.3))
    mapper = CommandMapper(car, 1 / 30)
    accel, speed = np.array([-2.0, -0.5, 0.0, 0.3, 1.0, 2.5]), np.full(6, 1.0)
    u = mapper.throttle_for_acceleration(accel, speed)
    # Independent check: the nominal car's acceleration at the throttle the motor really sees.
    x = np.maximum(np.abs(u) - 0.05, 0.0)
    seen = 0.75 * np.sign(u) * x * (1.0 + 0.3 * (x - 1.0))
    np.testing.assert_allclose(CommandMapper(CAR, 1 / 30).acceleration(seen, speed), accel, atol=1e-9)


def test_a_curved_throttle_map_is_named_as_its_curvature_not_as_drag():
    """The simulated car's motor sees x (1 + 0.5 (x - 1)) of the throttle x (a progressive map, full scale kept):
    the curvature is named and measured; drag, drift and the gain are not claimed."""
    import dataclasses

    from vehicles.dynamic_bicycle import ModelCoefficients, throttle_map

    # The map itself against a hand-worked value: u = 0.5, dead band 0.1, gain 2, c = 0.5: x = 0.4,
    # 2 * 0.4 * (1 + 0.5 * (0.4 - 1)) = 0.56; slope 2 * (1 - 0.5 + 2 * 0.5 * 0.4) = 1.8.
    k = ModelCoefficients.from_params(dataclasses.replace(CAR, corrections=dataclasses.replace(
        CAR.corrections, throttle_gain=2.0, throttle_dead_band=0.1, throttle_curvature=0.5)))
    mapped, slope = throttle_map(np.array([0.5, -0.5, 0.05]), k)
    assert mapped == pytest.approx([0.56, -0.56, 0.0]) and slope == pytest.approx([1.8, 1.8, 0.0])
    result = _identify_a_car_with(throttle_curvature=0.5)
    assert [e.effect for e in result.selected] == ["throttle_curvature"]
    fitted = result.car_out.corrections
    assert fitted.throttle_curvature == pytest.approx(0.5, abs=0.1)
    assert fitted.extra_drag_n_per_mps2 == 0.0 and fitted.motor_force_drift_per_s == 0.0
    assert fitted.throttle_gain == 1.0
