"""What an output-error fit's residual says, and whether its likelihood holds.

The innovations (the residual whitened by the fit's noise model) of each channel are tested for whiteness and
for independence of every input (:func:`symsbl._data.residuals.residual_test`): a residual that depends on the
inputs says the model is wrong, an input that depends on past residuals says the record was taken in a closed
loop, and innovations that stay correlated say the noise model does not describe the residual.

Output error is efficient when its likelihood holds: measurement noise its noise model describes, an input
measured without noise, an open loop. The equation error in the weak form is consistent under the conditions
that break it: process noise (a random force not in the record is equation noise), noise on the measured input
(each window averages it), feedback (the inverse model regresses the input on the measured motion). Measured
on a hardening oscillator over 20 seeds (white, AR(2) 20 dB measurement noise, band-limited process noise, 1 %
and 3 % noise on the measured force): the weak-form estimate was exact in 100/100 fits with coefficient z-scores
of spread 0.71-1.36 in every case; the output error's, with its noise model, 0.76-1.29 under measurement noise
only and 2-12 under process or input noise, where the innovations' Ljung-Box test rejected whiteness in 80-95 %
of the fits (0 % under measurement noise). :func:`doubts` lists what says the likelihood does not hold:

- the innovations are not white (Ljung-Box, :data:`symsbl._data.residuals.LEVEL`) while independent of the
  inputs (a residual the inputs explain is a missing term, which the selection is there to find);
- an input depends on past residuals (feedback);
- a measured input carries noise (its periodogram above a quarter of the sampling rate) above
  :data:`INPUT_NOISE` of the outputs' smallest relative noise (errors in variables).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .._base.blas import one_blas_thread
from .._data.residuals import ResidualTest, residual_test
from .._data.trajectory import spectral_noise_std
from .noise import innovations

__all__ = ["residual_tests", "as_record", "doubts", "noisy_inputs", "Doubts", "INPUT_NOISE"]

#: A measured input's relative noise (white-noise level over its spread) above this share of the outputs'
#: smallest relative noise flags errors in variables.
INPUT_NOISE = 0.3

#: Lags of the residual tests (MATLAB's ``resid`` default).
LAGS = 25


def residual_tests(engine, sol) -> list[ResidualTest]:
    """The residual test of every measured channel of ``engine`` at the solution ``sol``."""
    with one_blas_thread():  # many small least-squares fits: threads cost more than they bring
        return _tests(engine, sol)


def _tests(engine, sol) -> list[ResidualTest]:
    """:func:`residual_tests`, on segments long enough for the test's lags."""
    passes = engine.passes
    n = passes.records.n_total
    seg = passes.segments(sol.starts)
    with np.errstate(all="ignore"):
        R = passes.records.Y - passes.outputs(sol.theta, sol.X0, seg)
    U = passes.UN[:n]
    noise = sol.noise
    p = noise.order
    ends = np.append(seg.starts[1:], n)
    # each record's innovations in units of its own noise: records of different noise levels pooled raw would
    # inflate the correlations' spread (by 1.8 for two halves at 1:4) and the tests would reject white noise;
    # and each record's inputs in units of their spread there, for the same reason
    scale = np.sqrt(passes.per_record(sol.w))[seg.record_of_segment]
    spread = np.array([np.std(U[a : a + m], axis=0) for a, m in zip(passes.records.starts, passes.records.lengths)])
    u_scale = (1.0 / np.where(spread > 0, spread, 1.0))[seg.record_of_segment]
    out = []
    for c, name in enumerate(engine.measured):
        es, us = [], []
        for k, (a, b) in enumerate(zip(seg.starts, ends)):
            if b - a <= p + 2 * LAGS:
                continue
            e = (innovations(R[a:b, c], noise.ar[c]) if p else R[a:b, c]) * scale[k, c]
            keep = np.isfinite(e)
            es.append(e[keep])
            us.append(U[a + p : b][keep] * u_scale[k])
        if not es:
            continue
        e, u = np.concatenate(es), np.concatenate(us)
        if e.size <= 4 * LAGS:
            continue
        inputs = {m: u[:, k] for k, m in enumerate(engine.model.input_names) if np.std(u[:, k]) > 0}
        out.append(
            residual_test(
                name,
                e,
                inputs,
                LAGS,
                int(np.count_nonzero(noise.ar[c])) if p else 0,
                family=len(engine.measured) * max(len(engine.model.input_names), 1),
            )
        )
    return out


def as_record(t: ResidualTest) -> dict:
    """A residual test as the model file records it (plain values)."""
    return {
        "channel": t.channel,
        "samples": t.n_samples,
        "lags": t.lags,
        "whiteness_p": float(t.whiteness_p),
        "input_ratio": t.input_ratio,
        "feedback_ratio": t.feedback_ratio,
        "white": t.white,
        "independent": t.independent,
        "open_loop": t.open_loop,
        "predictable": float(t.predictable),
    }


def _relative_noise(values: list[np.ndarray]) -> float:
    """The white-noise standard deviation of a column over its spread, pooled over the records."""
    spread = float(np.std(np.concatenate(values)))
    sizes = np.array([v.size for v in values], dtype=float)
    var = float(np.sum(sizes * np.array([spectral_noise_std(v) ** 2 for v in values])) / max(sizes.sum(), 1.0))
    return math.sqrt(var) / spread if spread > 0 else 0.0


@dataclass(frozen=True)
class Doubts:
    """Why an output-error fit's likelihood does not hold, one line each, and whether the record is closed-loop or
    its measured input noisy (where output error is biased on segments of any length, and the equation error,
    the inverse model's or averaged over each window, is not)."""

    reasons: tuple = ()
    closed_loop: bool = False
    input_noise: bool = False

    @property
    def biased(self) -> bool:
        """Output error is biased on any segments: the equation error's estimate is the one to report."""
        return self.closed_loop or self.input_noise

    def __bool__(self) -> bool:
        return bool(self.reasons)


def noisy_inputs(records, measured, inputs) -> tuple[str, ...]:
    """The measured inputs of ``records`` whose white-noise level exceeds :data:`INPUT_NOISE` of the ``measured``
    outputs' smallest (errors in variables), one line each: a property of the data, not of a fit."""
    outputs = [_relative_noise([r.column(m) for r in records]) for m in measured]
    floor = min((o for o in outputs if o > 0), default=0.0)
    reasons = []
    for name in inputs:
        level = _relative_noise([r.column(name) for r in records])
        if floor > 0 and level > INPUT_NOISE * floor:
            reasons.append(
                f"the measured input {name} carries noise ({100 * level:.2g} % of its spread, against "
                f"{100 * floor:.2g} % on the outputs): errors in variables"
            )
    return tuple(reasons)


def doubts(tests: list[ResidualTest], noisy: tuple[str, ...] = ()) -> Doubts:
    """What doubts an output-error fit whose residual tests are ``tests``, its records' inputs being ``noisy``
    (:func:`noisy_inputs`); empty when its likelihood holds as far as the records tell."""
    reasons, loop = [], False
    for t in tests:
        if not t.white and t.independent:  # a residual the input explains is a missing term: the selection's job
            reasons.append(
                f"the innovations of {t.channel} are not white (Ljung-Box p = {t.whiteness_p:.2g}, "
                f"{100 * t.predictable:.2g} % of their variance predictable from their past): "
                "process noise, input noise or model error"
            )
        fed = sorted(k for k, r in t.feedback_ratio.items() if r > 1)
        if fed:
            loop = True
            reasons.append(f"{', '.join(fed)} depend(s) on past residuals of {t.channel}: a closed loop")
    return Doubts(tuple(reasons) + tuple(noisy), loop, bool(noisy))
