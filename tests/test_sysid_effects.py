"""Effects beyond the nominal model (docs/sysid.md, issue 16): the actuator chain of the predictors
against the simulator, the simulator's new effects against hand-worked physics, and identification
on generated logs whose truth the tool never sees (the simulator in sim/ at 2 ms physics steps
makes the logs; the 5-minute versions of these cases are `python -m app sysid-bench`)."""

import dataclasses
import math
from functools import lru_cache

import numpy as np
import pytest

from sim import SimEffects, Simulator
from sysid.data import build_trajectory
from sysid.diagnose import SysidSettings, identify
from sysid.generate import ExcitationSettings, effects_as_corrections, generate_log, parse_effects
from sysid.model import actuation
from tracks import load_track
from vehicles.params import CarParams, OtherTermsParams, load_car_params

NOMINAL = load_car_params("buzzracer")
MINUTES = 0.6
SETTINGS = SysidSettings(fit_max_starts=100, heldout_max_starts=400, n_bootstrap=300)
HARD_THROTTLE = ExcitationSettings(throttle_dither=0.3, dither_corner_hz=8.0)  # steps the rate limit shapes


# ----------------------------------------------------------------------------- actuator chain
class _Commands:
    """The fields sysid.model.actuation reads from a Trajectory."""

    def __init__(self, dt: float, throttle: np.ndarray, steering: np.ndarray) -> None:
        self.dt = dt
        self.t = dt * np.arange(throttle.size)
        self.throttle, self.steering = throttle, steering
        self.seg_start = np.zeros(throttle.size, dtype=int)


def test_actuation_is_the_simulators_actuator_chain():
    """Delay, limits, rate limits, play and asymmetry: the predictor's per-sub-step means against the
    simulator's linkage input sampled every 1 ms physics step (an independent implementation)."""
    dt, n = 0.032, 90  # 32 physics steps per sample
    rng = np.random.default_rng(7)
    steering = np.repeat(rng.uniform(-0.6, 0.6, n // 3), 3)  # beyond the 0.47 rad limit, reversing
    throttle = np.repeat(rng.uniform(-0.4, 1.0, n // 3), 3)
    corrections = dict(steering_delay_s=0.047, throttle_delay_s=0.021, steering_backlash_rad=0.08,
                       steering_gain_asymmetry=0.2)
    car = dataclasses.replace(NOMINAL, corrections=dataclasses.replace(NOMINAL.corrections, **corrections))
    sim = Simulator(load_track("oval"), [car])
    sim.reset([[2.5, 0.5, 0.0, 0.8, 0.0, 0.0]])
    fine = []
    for u, s in zip(throttle, steering):
        for _ in range(32):
            sim.step([[u, s]], 0.001)
            fine.append(sim.linkage_inputs(0))
    fine = np.array(fine).reshape(n, 2, 16, 2).mean(axis=2)  # (sample, sub-step, [throttle, linkage])
    first = np.array([10])
    ours = actuation(_Commands(dt, throttle, steering), first, n - 10, car, 2)
    # The simulator starts at rest with zero inputs; from sample 10 on both have forgotten the start.
    np.testing.assert_allclose(ours.throttle[0], fine[10:, :, 0], atol=0.02)
    # The play is exact on the ramp-then-hold path; the asymmetry scales each sub-step's mean angle (not
    # the path), which differs where the angle crosses zero inside a sub-step.
    np.testing.assert_allclose(ours.steering[0], fine[10:, :, 1], atol=0.011)
    # Without the play the linkage follows the rate-limited servo; the play changes it by up to b / 2.
    no_play = dataclasses.replace(car, corrections=dataclasses.replace(car.corrections, steering_backlash_rad=0.0))
    plain = actuation(_Commands(dt, throttle, steering), first, n - 10, no_play, 2)
    assert 0.03 < np.max(np.abs(plain.steering - ours.steering)) <= 0.5 * 0.08 * 1.2 + 1e-9


# ----------------------------------------------------------------------------- simulator effects
def test_simulator_play_holds_the_wheels_until_the_command_crosses_the_dead_band():
    b = 0.1
    fast = dataclasses.replace(NOMINAL.actuators, steering_rate_limit_radps=1e6)
    sim = Simulator(load_track("oval"), [dataclasses.replace(NOMINAL, actuators=fast)],
                    effects=SimEffects(steering_backlash_rad=b))
    sim.reset([[2.5, 0.5, 0.0, 0.5, 0.0, 0.0]])
    linkage = []
    for cmd in (0.3, 0.27, 0.23, 0.19, 0.1, 0.2):
        sim.step([[0.1, cmd]], 0.01)
        linkage.append(sim.linkage_inputs(0)[1])
    # Up to 0.3: dragged from 0 to 0.3 - b/2; back down inside the band: held; below it: dragged at + b/2.
    np.testing.assert_allclose(linkage, [0.25, 0.25, 0.25, 0.24, 0.15, 0.15], atol=1e-12)


def test_simulator_asymmetry_drift_and_unnamed_terms_against_hand_worked_values():
    track = load_track("oval")
    start = [[2.5, 0.5, 0.0, 1.0, 0.0, 0.0]]
    fast = dataclasses.replace(NOMINAL, actuators=dataclasses.replace(NOMINAL.actuators, steering_rate_limit_radps=1e6))
    sim = Simulator(track, [fast], effects=SimEffects(steering_gain_asymmetry=0.2))
    for cmd, want in ((0.2, 0.24), (-0.2, -0.16)):
        sim.reset(start)
        sim.step([[0.1, cmd]], 0.01)
        assert sim.linkage_inputs(0)[1] == pytest.approx(want, abs=1e-12)

    # Drift: the motor term of the acceleration, Cm1 u rate t / m, is what changes after t seconds.
    def initial_acceleration(drift_start: float) -> float:
        s = Simulator(track, [NOMINAL], effects=SimEffects(motor_force_drift_per_s=0.002, drift_start_s=drift_start))
        s.reset(start, initial_inputs=[[0.5, 0.0]])
        s.step([[0.5, 0.0]], 0.002)
        return (s.state(0)[3] - 1.0) / 0.002

    lost = initial_acceleration(0.0) - initial_acceleration(100.0)
    expected = NOMINAL.longitudinal.motor_force_n * 0.5 * 0.002 * 100.0 / NOMINAL.inertia.mass_kg
    assert lost == pytest.approx(expected, rel=0.02)

    # [other_terms]: a constant heading rate of 0.4 rad/s turns a car that stands still by 0.4 rad in 1 s.
    turning = dataclasses.replace(NOMINAL, other_terms=OtherTermsParams(yaw_rate_1=0.4))
    s = Simulator(track, [turning])
    s.reset([[2.5, 0.5, 0.0, 0.0, 0.0, 0.0]])
    for _ in range(10):
        s.step([[0.0, 0.0]], 0.1)
    assert s.state(0)[2] == pytest.approx(0.4, abs=1e-6)


# ----------------------------------------------------------------------------- identification
@lru_cache(maxsize=None)
def _identified(spec: str, seed: int, track: str = "oval", driver: str = "pursuit", hard: bool = False,
                other: tuple = ()):
    car = dataclasses.replace(NOMINAL, other_terms=OtherTermsParams(**dict(other))) if other else NOMINAL
    log = generate_log(car, parse_effects(spec), MINUTES, seed=seed, physics_dt=0.002, track=track, driver=driver,
                       excitation=HARD_THROTTLE if hard else ExcitationSettings())
    return identify(build_trajectory(log), NOMINAL, SETTINGS)


def _deviation(field: str, value: float) -> float:
    return value - 1.0 if field in ("steering_gain", "tire_grip_scale") else value


def _check(result, spec: str, names: set[str]):
    assert {e.effect for e in result.selected} == names
    truth = {k: v for k, v in effects_as_corrections(parse_effects(spec)).items()
             if v != getattr(CarParams().corrections, k)}
    for field, value in truth.items():
        got = getattr(result.car_out.corrections, field)
        assert abs(_deviation(field, got) - _deviation(field, value)) <= 0.2 * abs(_deviation(field, value)), \
            f"{field}: fitted {got:.5g}, true {value}"
    # Measured against the nominal dynamic model (a clean log would give about 0).
    assert result.heldout_error_reduction >= 0.5
    assert not result.unnamed_effect_remains


@pytest.mark.parametrize("spec, seed", [
    ("steering_backlash=0.06", 41),
    ("steering_asymmetry=0.15", 42),
    ("motor_drift=0.006", 43),
    ("steering_backlash=0.06,steering_offset=0.03", 44),
])
def test_new_effects_are_named_measured_and_removed(spec, seed):
    _check(_identified(spec, seed), spec, set(parse_effects(spec)))


def test_unseen_track_and_driver():
    spec = "steering_asymmetry=0.15,longitudinal_drag=0.03"
    _check(_identified(spec, 45, track="twisty", driver="stanley"), spec, {"steering_asymmetry", "longitudinal_drag"})


def test_declared_rate_limits_leave_nothing_to_explain_under_hard_throttle_steps():
    result = _identified("", 46, hard=True)
    assert not result.significant and result.car_out == NOMINAL
    # The delay candidate alone finds no throttle lag worth a third of a sample (before the rate limits were
    # modelled, such steps gave a claimed false throttle delay of about 11 ms).
    delay = next(c for c in result.candidates if c.effect == "actuation_delay")
    assert not delay.significant and delay.params["throttle_delay_s"] < 1 / 90
    assert abs(result.heldout_error_reduction) < 0.02


def test_an_effect_outside_the_library_of_names_is_reported_as_other_and_written():
    # Torque steer: the heading rate grows with throttle x speed. No named candidate has that shape; a
    # steering offset mimics it at the mean throttle and is fitted first, then dropped: by the keep test
    # (it worsens the held-out speed error by 6 %) before the terms are tried.
    result = _identified("", 47, other=(("yaw_rate_u_v", 0.5),))
    assert [e.effect for e in result.selected] == ["other"] and result.unnamed_effect_remains
    assert result.car_out.corrections == NOMINAL.corrections
    assert result.car_out.other_terms.yaw_rate_u_v == pytest.approx(0.5, rel=0.2)
    assert result.heldout_error_reduction >= 0.5
    offset = next(c for c in result.candidates if c.effect == "steering_offset")
    assert offset.heldout_error_reduction > 0.3 and offset.speed_reduction < -0.05  # position only: not kept


# ----------------------------------------------------------------------------- planner's command mapping
def test_command_mapping_puts_the_wheels_where_planned_through_play_and_asymmetry():
    """The planner's mapper with the identified play and asymmetry, commanding the simulator's car that
    has them: after each step the wheel angle (gain * linkage + offset) is the planned one."""
    from planning.commands import CommandMapper

    corr = dict(steering_backlash_rad=0.06, steering_gain_asymmetry=0.15, steering_offset_rad=0.02,
                steering_gain=0.9)
    fast = dataclasses.replace(NOMINAL.actuators, steering_rate_limit_radps=1e6)
    car = dataclasses.replace(NOMINAL, actuators=fast, corrections=dataclasses.replace(NOMINAL.corrections, **corr))
    mapper = CommandMapper(car, 0.02)
    sim = Simulator(load_track("oval"), [dataclasses.replace(car, corrections=NOMINAL.corrections)],
                    effects=SimEffects(steering_backlash_rad=0.06, steering_gain_asymmetry=0.15,
                                       steering_offset_rad=0.02, steering_gain=0.9))
    sim.reset([[2.5, 0.5, 0.0, 0.5, 0.0, 0.0]])
    planned = [0.1, 0.2, 0.15, 0.16, -0.1, -0.05, -0.2, 0.0, 0.3]
    for delta in planned:
        throttle, steering = mapper.commands(0.0, delta, speed=0.5)
        sim.step([[throttle, steering]], 0.02)
        wheel = 0.9 * sim.linkage_inputs(0)[1] + 0.02
        assert wheel == pytest.approx(delta, abs=1e-9)
    # Without the mapper's play compensation the reversals miss by up to half the play (times the gain).
    plain = CommandMapper(dataclasses.replace(car, corrections=dataclasses.replace(
        car.corrections, steering_backlash_rad=0.0)), 0.02)
    sim.reset([[2.5, 0.5, 0.0, 0.5, 0.0, 0.0]])
    misses = []
    for delta in planned:
        sim.step([list(plain.commands(0.0, delta, speed=0.5))], 0.02)
        misses.append(abs(0.9 * sim.linkage_inputs(0)[1] + 0.02 - delta))
    assert max(misses) > 0.02
