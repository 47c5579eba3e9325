"""bench/race_perturbations.py: its late commands against the simulator's own actuation-delay FIFO
(an independent mechanism), and its neutral pulses against zero commands stepped by hand."""
import numpy as np
import pytest

from bench.race_perturbations import perturbed_simulator
from sim import SimEffects, Simulator

PERIOD = 1.0 / 30.0
START = [[0.0, 0.0, 0.0, 1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 1.0, 0.0, 0.0]]
COMMANDS = [[[0.6, 0.1], [0.2, -0.2]], [[0.9, -0.25], [0.4, 0.3]], [[-0.3, 0.2], [0.8, 0.0]], [[0.5, 0.0], [0.1, 0.1]]]


def _run(sim):
    sim.reset(START)
    for cmd in COMMANDS:
        sim.step(cmd, PERIOD)
    return sim.states


@pytest.mark.parametrize("options", [{"late_ms": (12.0, 12.0)}, {"tail": (1.0, 12.0, 12.0)}])
def test_late_commands_equal_an_actuation_delay(track, car, options):
    """Every command 12 ms late (the previous one acting meanwhile) is a 12 ms actuation delay."""
    late = _run(perturbed_simulator(**options)(track, [car, car]))
    fifo = _run(Simulator(track, [car, car], effects=SimEffects(steering_delay_s=0.012, throttle_delay_s=0.012)))
    np.testing.assert_allclose(late, fifo, atol=1e-12)


def test_neutral_pulse_precedes_every_command(track, car):
    pulsed = _run(perturbed_simulator(neutral=(1.0, 8.0))(track, [car, car]))
    ref = Simulator(track, [car, car])
    ref.reset(START)
    for cmd in COMMANDS:
        ref.step(np.zeros((2, 2)), 0.008)
        ref.step(cmd, PERIOD - 0.008)
    np.testing.assert_allclose(pulsed, ref.states, atol=1e-12)


def test_no_options_is_the_plain_simulator(track, car):
    np.testing.assert_allclose(_run(perturbed_simulator()(track, [car, car])), _run(Simulator(track, [car, car])), atol=0)
