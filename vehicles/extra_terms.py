"""Additive terms of an effect that model identification could not name (docs/sysid.md, "other").

The library is functions of speed v (m/s), throttle u (-1..1, after the actuators) and wheel
angle d (rad). A car's ``[other_terms]`` table holds one coefficient per term and rate:
d(speed)/dt += sum accel_<term> * term, d(heading)/dt += sum yaw_rate_<term> * term.
The simulator and the identification's predictors apply them through :func:`extra_rates`.
Works on floats and on numpy arrays (the same functions, no numpy-only calls).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from vehicles.params import CarParams, OtherTermsParams

# Term label (as reported) -> (field suffix in [other_terms], function of v, u, d).
LIBRARY: dict[str, tuple[str, Callable[[Any, Any, Any], Any]]] = {
    "1": ("1", lambda v, u, d: 1.0 + 0.0 * v),
    "v": ("v", lambda v, u, d: v),
    "v|v|": ("v_absv", lambda v, u, d: v * abs(v)),
    "u": ("u", lambda v, u, d: u + 0.0 * v),
    "u*v": ("u_v", lambda v, u, d: u * v),
    "d": ("d", lambda v, u, d: d + 0.0 * v),
    "d*v": ("d_v", lambda v, u, d: d * v),
    "d*v^2": ("d_v2", lambda v, u, d: d * v * v),
    "d|d|*v": ("d_absd_v", lambda v, u, d: d * abs(d) * v),
    "d^2*v^2": ("d2_v2", lambda v, u, d: d * d * v * v),
}


def coefficients(terms: OtherTermsParams) -> tuple[tuple[Callable, float, float], ...]:
    """(function, accel coefficient, yaw-rate coefficient) of each non-zero term."""
    out = []
    for suffix, fn in LIBRARY.values():
        ca, cy = getattr(terms, f"accel_{suffix}"), getattr(terms, f"yaw_rate_{suffix}")
        if ca != 0.0 or cy != 0.0:
            out.append((fn, ca, cy))
    return tuple(out)


def terms_from_coefficients(accel: dict[str, float], yaw_rate: dict[str, float]) -> OtherTermsParams:
    """[other_terms] for coefficients keyed by term label (labels of LIBRARY)."""
    values = {f"accel_{LIBRARY[k][0]}": float(c) for k, c in accel.items()}
    values |= {f"yaw_rate_{LIBRARY[k][0]}": float(c) for k, c in yaw_rate.items()}
    return OtherTermsParams(**values)


def extra_rates(v, u, d, terms: tuple[tuple[Callable, float, float], ...]):
    """(added d(speed)/dt, added d(heading)/dt) for ``coefficients(...)``; a coefficient may be an array
    broadcasting against ``v`` (several cars' terms in one batch)."""
    dv = 0.0 * v
    dth = 0.0 * v
    for fn, ca, cy in terms:
        t = fn(v, u, d)
        if np.any(ca != 0.0):
            dv = dv + ca * t
        if np.any(cy != 0.0):
            dth = dth + cy * t
    return dv, dth


def car_extra_terms(car: CarParams) -> tuple[tuple[Callable, float, float], ...]:
    return coefficients(car.other_terms)
