"""Fixtures shared by the racing tests: the shipped oval and the shipped 1/28-scale car."""
import pytest

from tracks import load_track
from vehicles.params import load_car_params


@pytest.fixture(scope="module")
def track():
    return load_track("oval")


@pytest.fixture(scope="module")
def car():
    return load_car_params("buzzracer")
