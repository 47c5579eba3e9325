"""Dynamics model descriptions. Each builds its C++ implementation (values and analytic derivatives
live only in C++: solver_cpp/src/dynamics.cpp) for a given time step."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import _core


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return value


@dataclass(frozen=True)
class KinematicBicycle:
    """Kinematic bicycle, state [px, py, v, theta], control [a, delta]; lf, lr in metres."""

    lf: float
    lr: float
    type: str = field(default="kinematic_bicycle", init=False)
    nx: int = field(default=4, init=False)
    nu: int = field(default=2, init=False)

    def build(self, dt: float, where: str = "dynamics") -> _core.Dynamics:
        return _core.KinematicBicycle(_positive(f"{where}.lf", self.lf), _positive(f"{where}.lr", self.lr), dt)


@dataclass(frozen=True)
class KinematicBicycleFrenet:
    """Kinematic bicycle in track coordinates, state [s, ey, v, epsi], control [a, delta].

    kappa: curvature (1/m) sampled every ds metres along the centre line (periodic if closed)."""

    lf: float
    lr: float
    kappa: np.ndarray
    ds: float
    closed: bool = True
    type: str = field(default="kinematic_bicycle_frenet", init=False)
    nx: int = field(default=4, init=False)
    nu: int = field(default=2, init=False)

    def build(self, dt: float, where: str = "dynamics") -> _core.Dynamics:
        kappa = np.asarray(self.kappa, dtype=float)
        if kappa.ndim != 1 or kappa.size < 2 or not np.all(np.isfinite(kappa)):
            raise ValueError(f"{where}.kappa must be a finite 1-D array with at least 2 samples")
        return _core.KinematicBicycleFrenet(
            _positive(f"{where}.lf", self.lf), _positive(f"{where}.lr", self.lr), dt, kappa,
            _positive(f"{where}.ds", self.ds), bool(self.closed))


@dataclass(frozen=True)
class LinearModel:
    """x_{k+1} = A x_k + B u_k (already discrete; dt is not used)."""

    A: np.ndarray
    B: np.ndarray
    type: str = field(default="linear", init=False)

    @property
    def nx(self) -> int:
        return int(np.asarray(self.A).shape[0])

    @property
    def nu(self) -> int:
        return int(np.asarray(self.B).shape[1])

    def build(self, dt: float, where: str = "dynamics") -> _core.Dynamics:
        A = np.asarray(self.A, dtype=float)
        B = np.asarray(self.B, dtype=float)
        if A.ndim != 2 or A.shape[0] != A.shape[1] or not np.all(np.isfinite(A)):
            raise ValueError(f"{where}.A must be a finite square matrix, got shape {A.shape}")
        if B.ndim != 2 or B.shape[0] != A.shape[0] or not np.all(np.isfinite(B)):
            raise ValueError(f"{where}.B must be finite with {A.shape[0]} rows, got shape {B.shape}")
        return _core.LinearDynamics(A, B)


Model = KinematicBicycle | KinematicBicycleFrenet | LinearModel
