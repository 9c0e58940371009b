"""The deflection sensitivity's share of every read-out's uncertainty (``data.invols_uncertainty``).

The deflection sensitivity (invols, m/V) converts the photodiode's volts into metres, so a relative error u of
it scales the whole measured deflection: x -> (1 + u) x, and with it every displacement, velocity and
acceleration, the left side Y = -(m x'' + c x' + k x) (exactly by 1 + u), the noise, and the separation
z = d - x the library's columns are evaluated at. Unlike k (which scales every coefficient exactly,
:mod:`afmid.fit.uncertainty`), the columns are nonlinear in z, so no single factor holds for every read-out
(a DMT modulus, F ~ E* z^(3/2), scales as (1 + u)^(-1/2); a Hamaker constant, F ~ H / z^2, as (1 + u)^3).
The sensitivity is therefore measured by refitting: the trace is prepared again with its deflection scaled by
(1 +- u), the columns are evaluated again, and the fit's own support is solved on them (a least-squares solve;
the support is not selected again). The half-difference of the two read-outs is the share (1 sigma).

The separation: a declared one (``sample.separation``) is a length the deflection's scale does not touch and is
kept (so the indentation changes by u times the amplitude: a large share on a stiff sample). An estimated one
(and an estimated decay length) was found on the deflection's own scale, so it is searched again on the scaled
record, starting from d (1 + u) (the exact minimiser for a force law without a length of its own; a0 is one):
measured on tests/configs/dmt.yaml with d estimated and u = 5 %, the scaled start alone gave the Hamaker
constant a share of 15.6 % where the full refit moves it by 5.6 % (d moved by 583 pm, not 599); searched
again, the shares follow the full refit (tests/fit/test_invols_share.py).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

import afmid.fit.regression as regression
from afmid.fit.declared_drive import declared_drive, with_declared_drive
from afmid.fit.prepare import prepare, with_regressor_noise
from afmid.fit.system import build_system
from afmid.fit.uncertainty import add_half_difference, widen_interval
from afmid.preprocess.instrument import from_config as instrument_from_config


def scaled_trace(trace, factor: float):
    """The trace with its deflection multiplied by ``factor`` (a new object; ``trace`` is not modified). The drive
    measured on loading is dropped (it was measured on the old samples): the caller passes the drive."""
    return dataclasses.replace(trace, deflection=trace.deflection * factor, drive=None)


def scaled_parameters(params: dict, nonlinear: dict, factor: float) -> dict:
    """The column parameters on a deflection scaled by ``factor``: the estimated lengths (unit m: the
    separation, decay lengths) scaled with it, the declared ones (a0, R, a declared separation) kept."""
    out = dict(params)
    for name, est in nonlinear.items():
        if est.unit == "m" and name in out:
            out[name] = params[name] * factor
    return out


def refit_scaled(prep, library, config, coef: np.ndarray, mask: np.ndarray, params: dict, nonlinear: dict,
                 factor: float, resettle=None) -> tuple[np.ndarray, dict, object]:
    """The fit's support solved on its trace with the deflection scaled by ``factor``: (coefficients, the column
    parameters used, the scaled trace). The record is cut at the fit's own drive frequency. ``resettle(prepared,
    parameters) -> parameters`` searches the estimated nonlinear parameters again on the scaled record from
    their scaled values (the fit's profile on its support; None: the scaled values are kept)."""
    trace = scaled_trace(prep.trace, factor)
    drive = dataclasses.replace(prep.drive, amplitude=prep.drive.amplitude * factor,
                                offset=prep.drive.offset * factor)
    scaled = prepare(trace, config.fit, instrument_from_config(config), drive=drive)
    calibrated = declared_drive(config, trace)
    if calibrated is not None:
        scaled = with_declared_drive(scaled, calibrated)
    trial = scaled_parameters(params, nonlinear, factor)
    if resettle is not None and nonlinear:
        trial = resettle(scaled, trial)
    # The row weights with the regressors' own noise, as the fit's (from its coefficients: a weighting only).
    scaled = with_regressor_noise(scaled, library, trial, coef)
    system = build_system(scaled, library, trial)
    solved, _ = regression.subset_fit(regression.combine(system.T_blocks), mask)
    return solved, trial, trace


def propagate_invols(quantities: dict, prep, library, config, coef: np.ndarray, mask: np.ndarray, params: dict,
                     nonlinear: dict, read_out, resettle=None) -> float:
    """Add the deflection sensitivity's share (``config.data.invols_uncertainty``, relative 1 sigma) to every
    quantity in place: to its ``error_calibration`` in quadrature (beside k's and Q's), to its 1-sigma ``error`` and
    to both halves of its 95 % interval. Returns the force's relative share (1 sigma): the inverted force scales
    exactly with the deflection, so it is the declared relative uncertainty itself (0 when none is declared).

    ``read_out`` is :func:`afmid.fit.forces.read_out`; ``params`` the column parameters of the fit (d included),
    ``nonlinear`` its estimated nonlinear parameters (:class:`afmid.fit.search.NonlinearEstimate` by name),
    ``resettle`` as in :func:`refit_scaled`.
    """
    u = float(config.data.invols_uncertainty or 0.0)
    if u <= 0:
        return 0.0
    variance = dict.fromkeys(quantities, 0.0)
    sides = []
    for sign in (1, -1):
        solved, trial, trace = refit_scaled(prep, library, config, coef, mask, params, nonlinear, 1 + sign * u,
                                            resettle)
        sides.append(read_out(library, solved, None, trial, mask, trace))
    add_half_difference(variance, *sides)
    for name, q in quantities.items():
        share = math.sqrt(variance[name])
        if share <= 0:
            continue
        q["error_calibration"] = math.hypot(q.get("error_calibration", 0.0), share)
        widen_interval(q, share)
    return u
