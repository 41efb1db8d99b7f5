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

- the innovations are not white (Ljung-Box, :data:`symsbl._data.residuals.LEVEL`), their past predicts at least
  :data:`symsbl._data.residuals.COLOUR` of their variance (a colour that matters), and they are independent of the
  inputs (a residual the inputs explain is a missing term, which the selection is there to find) and, where
  the inputs are periodic, the measured noise between periods is not white either (a residual coloured over
  white noise is the model's error repeating with the excitation, not a disturbance), and the model's own
  simulated trajectory does not predict them out of sample (:data:`symsbl._data.residuals.MODEL_ERROR`; a
  disturbance the record lacks is independent of the trajectory the input drives, a law the model lacks is a
  function of it);
- an input depends on past residuals (feedback): on a record whose inputs are periodic, between periods (a
  model's error under a periodic input repeats, and a multisine's many lines correlate with it at every lag),
  elsewhere after what the past input explains of the residual is removed;
- a measured input carries noise above :data:`INPUT_NOISE` of the outputs' smallest relative noise (errors in
  variables), each signal's noise told from its excitation where it can be
  (:func:`symsbl._data.excitation.noise_std`: between periods of a periodic record, in the bands the excitation
  leaves quiet).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from itertools import combinations_with_replacement

import numpy as np

from .._base.blas import one_blas_thread
from .._data.excitation import aperiodic_part, period, predicted, relative_noise
from .._data.residuals import ResidualTest, explained_out_of_sample, ljung_box, residual_test
from .noise import innovations

__all__ = [
    "residual_tests",
    "as_record",
    "doubts",
    "noisy_inputs",
    "noisy_input_names",
    "loop_possible",
    "Doubts",
    "INPUT_NOISE",
]

#: A measured input's relative noise (white-noise level over its spread) above this share of the outputs'
#: smallest relative noise flags errors in variables.
INPUT_NOISE = 0.3

#: Lags of the residual tests (MATLAB's ``resid`` default).
LAGS = 25
#: Samples the residual tests read at most: a longer fit's segments are each tested on their first stretch (the
#: tests' levels hold at any length; on 262144 samples they cost a quarter of the refinement).
TEST_SAMPLES = 2**17


def _tested_ends(starts: np.ndarray, n: int) -> np.ndarray:
    """Where the tested stretch of each segment (``starts`` of ``n`` rows in all) ends."""
    ends = np.append(starts[1:], n)
    if n <= TEST_SAMPLES:
        return ends
    return starts + np.maximum((ends - starts) * TEST_SAMPLES // n, np.minimum(ends - starts, 4 * LAGS))


def residual_tests(engine, sol) -> list[ResidualTest]:
    """The residual test of every measured channel of ``engine`` at the solution ``sol``."""
    with one_blas_thread():  # many small least-squares fits: threads cost more than they bring
        return _tests(engine, sol)


def _tests(engine, sol) -> list[ResidualTest]:
    """:func:`residual_tests`, on segments long enough for the test's lags."""
    passes = engine.passes
    n = passes.records.n_total
    seg = passes.segments(sol.starts)
    X = passes.simulate(sol.theta, sol.X0, seg)
    with np.errstate(all="ignore"):
        R = passes.records.Y - passes.observed(X, sol.theta)
    U = passes.UN[:n]
    noise = sol.noise
    p = noise.order
    ends = _tested_ends(seg.starts, n)
    # each record's innovations in units of its own noise: records of different noise levels pooled raw would
    # inflate the correlations' spread (by 1.8 for two halves at 1:4) and the tests would reject white noise;
    # and each record's inputs in units of their spread there, for the same reason
    scale = np.sqrt(passes.per_record(sol.w))[seg.record_of_segment]
    spread = np.array([np.std(U[a : a + m], axis=0) for a, m in zip(passes.records.starts, passes.records.lengths)])
    u_scale = (1.0 / np.where(spread > 0, spread, 1.0))[seg.record_of_segment]
    periodic, R_loop, U_loop, Y_noise = _loop_parts(passes.records, R, U)
    foreseen = _predicted_inputs(passes.records, U)
    out = []
    for c, name in enumerate(engine.measured):
        es: list[np.ndarray] = []
        us: list[np.ndarray] = []
        loop_es: list[np.ndarray] = []
        loop_us: list[np.ndarray] = []
        for k, (a, b) in enumerate(zip(seg.starts, ends)):
            if b - a <= p + 2 * LAGS:
                continue
            # the residual between periods is noise, not modelled: the noise model, fitted to a residual that
            # holds the model's error, would colour it
            raw = periodic[seg.record_of_segment[k]]
            for r, x, ex, ux, whiten in ((R, U, es, us, True), (R_loop, U_loop, loop_es, loop_us, not raw)):
                e = (innovations(r[a:b, c], noise.ar[c]) if p and whiten else r[a + p : b, c]) * scale[k, c]
                keep = np.isfinite(e)
                ex.append(e[keep])
                ux.append(x[a + p : b][keep] * u_scale[k])
        if not es:
            continue
        e, u = np.concatenate(es), np.concatenate(us)
        loop_e, loop_u = np.concatenate(loop_es), np.concatenate(loop_us)
        if e.size <= 4 * LAGS or loop_e.size <= 4 * LAGS:
            continue
        names = engine.model.input_names
        inputs = {m: u[:, k] for k, m in enumerate(names) if np.std(u[:, k]) > 0}
        loop_inputs = _fed(names, u, loop_u, foreseen)
        test = residual_test(
            name,
            e,
            inputs,
            LAGS,
            int(np.count_nonzero(noise.ar[c])) if p else 0,
            family=len(engine.measured) * max(len(names), 1),
            loop=(loop_e, loop_inputs),
        )
        between = Y_noise[:, c][np.isfinite(Y_noise[:, c])]
        noise_p = ljung_box(between, LAGS)[1] if between.size > 4 * LAGS else test.noise_p
        traced = _traced(R[:, c], X, U, (seg.starts, ends), noise.ar[c] if p else ())
        out.append(dataclasses.replace(test, noise_p=noise_p, trajectory=traced))
    return out


#: Lags of the model's trajectory (besides the present) in the regression that tells its error from a disturbance.
TRAJECTORY_LAGS = 2

#: Columns of :func:`trajectory_basis` at most: its cubic monomials while they fit, else fewer cross products.
BASIS_COLUMNS = 120

#: Rows of the trajectory regression at most (every k-th row beyond: each row keeps its own lags).
TRAJECTORY_ROWS = 50_000


def trajectory_basis(X: np.ndarray, U: np.ndarray, scaled_by: tuple | None = None) -> np.ndarray:
    """Functions of a model's simulated states ``X`` ``(n_samples, n_states)`` and inputs ``U`` that its error may
    follow: the states' monomials to degree 3 (robustly scaled and clipped, so that a simulation running away in
    one segment does not dominate; cross products dropped, degree by degree from the highest, while more than
    :data:`BASIS_COLUMNS`) and the inputs, each scaled by its spread over ``scaled_by`` (states and inputs;
    default ``X`` and ``U``). A disturbance the record lacks is independent of all of them."""
    Xs, Us = (X, U) if scaled_by is None else scaled_by
    with np.errstate(all="ignore"):
        centre = np.nanmedian(Xs, axis=0)
        spread = np.nanpercentile(Xs, 75, axis=0) - np.nanpercentile(Xs, 25, axis=0)
        Z = np.clip(np.nan_to_num((X - centre) / np.where(spread > 0, spread, 1.0)), -10.0, 10.0)
        mean, scale = np.mean(Us, axis=0), np.std(Us, axis=0)
    n_states = Z.shape[1]
    columns = [Z[:, j] ** d for d in (1, 2, 3) for j in range(n_states)]
    for degree in (2, 3):
        crossed = [c for c in combinations_with_replacement(range(n_states), degree) if len(set(c)) > 1]
        if len(columns) + len(crossed) > BASIS_COLUMNS:
            break
        columns += [np.prod(Z[:, list(c)], axis=1) for c in crossed]
    V = np.nan_to_num((U - mean) / np.where(scale > 0, scale, 1.0))
    return np.column_stack(columns + [V[:, j] for j in range(V.shape[1]) if scale[j] > 0])


def _traced(r: np.ndarray, X: np.ndarray, U: np.ndarray, spans: tuple, ar) -> float:
    """:func:`symsbl._data.residuals.explained_out_of_sample` of one channel's innovations (its residual ``r``
    filtered by its noise model's ``ar``, as :func:`symsbl._data.residuals.innovations` does) by
    :func:`trajectory_basis` of the simulated states ``X`` and inputs ``U`` at the same sample and
    :data:`TRAJECTORY_LAGS` before, within each segment (``spans``: their starts and ends, each simulated from its
    own initial state); every k-th sample beyond :data:`TRAJECTORY_ROWS`."""
    L, p = TRAJECTORY_LAGS, len(ar)
    step = max(1, -(-r.size // TRAJECTORY_ROWS))  # at most TRAJECTORY_ROWS rows: of 98304 samples every second
    es, at = [], []
    for a, b in zip(*spans):
        if b - a <= p + 4 * (L + 1):
            continue
        at_rows = a + p + np.arange(L, b - a - p, step)
        e = r[at_rows] + sum(c * r[at_rows - i] for i, c in enumerate(ar, start=1))  # the innovations there
        keep = np.isfinite(e)
        es.append(e[keep])
        at.append(at_rows[keep])
    if not es:
        return float("nan")
    e, where = np.concatenate(es), np.concatenate(at)
    rows = np.concatenate([where - k for k in range(L + 1)])  # every lag's rows, scaled once together
    once, back = np.unique(rows, return_inverse=True)  # each sample's functions once: the lags share most rows
    B = trajectory_basis(X[once], U[once], (X[::step], U[::step]))[back.reshape(L + 1, -1)]
    A = B.transpose(1, 0, 2).reshape(B.shape[1], B.shape[0] * B.shape[2])  # the lags side by side
    if e.size <= 4 * A.shape[1]:
        return float("nan")
    return explained_out_of_sample(e, A)


#: An input whose change from period to period is below this share of its spread repeats exactly (a record
#: simulated, or a generator's output logged without noise).
EXACT = 1e-9


def loop_possible(engine) -> bool:
    """Whether a loop could feed back into an input of ``engine``'s records: one that its own past does not
    predict (:func:`_predicted_inputs`)."""
    passes = engine.passes
    U = passes.UN[: passes.records.n_total]
    return len(_predicted_inputs(passes.records, U)) < U.shape[1]


def _fed(names, u: np.ndarray, loop_u: np.ndarray, predicted: set[int]) -> dict:
    """The inputs a loop could feed back into, by name, as the loop test reads them (``loop_u``): not one that
    repeats exactly from period to period, nor one that its own past predicts (``predicted``)."""
    return {
        m: loop_u[:, k]
        for k, m in enumerate(names)
        if np.std(loop_u[:, k]) > EXACT * np.std(u[:, k]) and k not in predicted
    }


def _predicted_inputs(records, U: np.ndarray) -> set[int]:
    """The columns of ``U`` that every record's own past predicts within :data:`EXACT` of their spread (a noise-free
    sine or multisine: :func:`symsbl._data.excitation.predicted`), judged on each record's first
    :data:`TEST_SAMPLES`."""
    spans = list(zip(records.starts, np.minimum(records.lengths, TEST_SAMPLES)))
    return {k for k in range(U.shape[1]) if all(predicted(U[a : a + m, k], EXACT) for a, m in spans)}


def _loop_parts(records, R: np.ndarray, U: np.ndarray):
    """Whether each record's inputs are periodic, and the residual ``R``, the inputs ``U`` and the measured
    outputs between periods (:func:`_between_periods`: the residual and the inputs as they are, the outputs NaN,
    where the inputs are not periodic)."""
    spans = list(zip(records.starts, records.lengths))
    periods = [period(U[a : a + m]) if U.shape[1] else None for a, m in spans]
    periodic = np.array([L is not None for L in periods], dtype=bool)
    between = [_between_periods(X, spans, periods, other) for X, other in ((R, R), (U, U), (records.Y, np.nan))]
    return periodic, *between


def _between_periods(X: np.ndarray, spans, periods, elsewhere) -> np.ndarray:
    """``X`` where only noise and a loop can show: in each record (``spans``: start, length) whose inputs have a
    period (``periods``, samples or None; :func:`symsbl._data.excitation.period`), the part of ``X`` that does
    not repeat from period to period over all but the last whole period
    (:func:`symsbl._data.excitation.aperiodic_part`; a model's error under a periodic input repeats, the noise
    does not, nor what a loop feeds back of it, and a transient that has not passed colours the part, which the
    test's band allows for), the rest of the record NaN; ``elsewhere`` (an array like ``X``, or a value) in the
    records that are not periodic."""
    out = np.array(np.broadcast_to(elsewhere, X.shape), dtype=float)
    for (a, m), L in zip(spans, periods):
        if L is None:
            continue
        whole = (m // L - 1) * L
        out[a : a + whole] = aperiodic_part(X[a : a + m], L)
        out[a + whole : a + m] = np.nan
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
        "noise_p": float(t.noise_p) if np.isfinite(t.noise_p) else None,
        "trajectory": float(t.trajectory) if np.isfinite(t.trajectory) else None,
    }


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
    outputs' smallest (errors in variables), one line each: a property of the data, not of a fit. Outputs whose
    noise the record does not resolve (:data:`~symsbl._data.excitation.RESOLVED`) are left out; with none left,
    no input is flagged."""
    floor, flagged = _noisy(records, measured, inputs)
    return tuple(
        f"the measured input {name} carries noise ({100 * level:.2g} % of its spread, against "
        f"{100 * floor:.2g} % on the outputs): errors in variables"
        for name, level in flagged.items()
    )


def noisy_input_names(records, measured, inputs) -> tuple[str, ...]:
    """The names of the inputs :func:`noisy_inputs` flags."""
    return tuple(_noisy(records, measured, inputs)[1])


def _noisy(records, measured, inputs) -> tuple[float, dict]:
    """The outputs' smallest relative noise and ``{input: its relative noise}`` of the inputs above
    :data:`INPUT_NOISE` of it."""
    periods = [period(r.inputs) if r.inputs.size else None for r in records]
    outputs = [relative_noise([r.column(m) for r in records], periods) for m in measured]
    floor = min((o for o in outputs if np.isfinite(o)), default=0.0)
    levels = {name: relative_noise([r.column(name) for r in records], periods) for name in inputs}
    return floor, {n: lv for n, lv in levels.items() if floor > 0 and lv > INPUT_NOISE * floor}


def doubts(tests: list[ResidualTest], noisy: tuple[str, ...] = ()) -> Doubts:
    """What doubts an output-error fit whose residual tests are ``tests``, its records' inputs being ``noisy``
    (:func:`noisy_inputs`); empty when its likelihood holds as far as the records tell."""
    reasons, loop = [], False
    for t in tests:
        # a residual the input explains is a missing term, and one coloured over a white noise (told between
        # periods) or one its own trajectory predicts the model's error: the selection's and the model choice's
        # to judge, not the likelihood's; a colour its past barely predicts does not matter
        if not t.white and t.coloured and t.independent and not t.noise_white and not t.model_error:
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
