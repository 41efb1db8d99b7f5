"""The initial state of a record for a given model: fitted to the record's first samples, not read off them.

Starting a re-simulation from the first measured sample carries that sample's noise into the whole
response: for a lightly damped system it decays slowly, for a limit cycle or a chaotic system it
never does (a phase error on a limit cycle persists), and an unmeasured state (a velocity from a
displacement-only record, a latent state) has no first sample at all. :func:`initial_state` instead
fits the state at the record's start to the measured states over a stretch of the record (Gauss-
Newton with the coefficients fixed), as the output-error refinement does for its segments.
"""

from __future__ import annotations

import numpy as np

from .._data.trajectory import Trajectory
from .._model import IdentifiedModel
from .problem import Parameterisation, Records
from .rows import state_guess
from .sensitivity import Passes
from .smoothing import smooth_model, smoothing_widths
from .solver import PHI_STOP, Iterate, _growth, _state_scale, horizon, initial_states, noise_precisions

__all__ = ["initial_state", "fitted_start", "short_horizons"]


#: The first stretch fitted (samples) and the factor by which it grows up to the stretch asked for. One long
#: stretch fitted from a poor guess (an unmeasured velocity estimated at the record's noisy edge) can end in
#: another basin of a nonlinear response: measured on a 6001-sample, displacement-only record of a 2-DOF chain
#: with a cubic spring, 35 % NRMSE from the whole record at once, 1.0 % (its noise) grown from 256 samples.
FIRST_STRETCH, GROWTH = 256, 8
#: Gauss-Newton sweeps of a stretch's fit at most.
SWEEPS = 8
#: Samples times passes from which a stretch's passes are compiled: a pass of fixed coefficients costs about
#: 0.6 us a sample on CasADi's virtual machine and 0.1 us compiled, and compiling it about 0.25 s of gcc
#: (measured on a Duffing oscillator; both grow with the model), so a validation record of 8192 samples
#: fitted in at most nine passes runs sooner uncompiled.
COMPILED_WORK = 2**19


def initial_state(
    model: IdentifiedModel,
    data: Trajectory,
    observed,
    guess: np.ndarray,
    *,
    interpolation: str,
    substeps: int,
    length: int,
) -> np.ndarray:
    """The state at ``data``'s first sample that best explains its first ``length`` samples.

    The stretch grows from :data:`FIRST_STRETCH` samples by :data:`GROWTH`, each fit starting from the last.

    Parameters
    ----------
    model : IdentifiedModel
    data : Trajectory
        Holds the ``observed`` states and the model's inputs.
    observed : sequence of str
        The model's states measured in ``data``.
    guess : ndarray, shape (n_states,)
        The starting guess (the first sample; estimates for the unmeasured states).
    interpolation, substeps : as in :func:`symsbl.refine`.
    length : int
        Samples used (longer is more precise for a damped system, but a chaotic one amplifies errors
        beyond the length an output-error fit stopped at).
    """
    return fitted_start(model, data, observed, guess, interpolation=interpolation, substeps=substeps, length=length)[0]


def fitted_start(
    model: IdentifiedModel,
    data: Trajectory,
    observed,
    guess: np.ndarray,
    *,
    interpolation: str,
    substeps: int,
    length: int,
) -> tuple[np.ndarray, int | None]:
    """:func:`initial_state`, and the samples within which the model amplifies a state error
    :data:`~symsbl._refine.solver.PHI_STOP`-fold on ``data`` (from the growth over the fitted stretch; None
    when it does not grow)."""
    n = max(8, min(int(length), data.n_samples))
    x0 = np.asarray(guess, dtype=float)
    span = min(n, FIRST_STRETCH)
    while True:
        worth = span == n and span * (SWEEPS + 1) >= COMPILED_WORK
        x0, phi = _fit(
            model, data.slice(0, span), observed, x0, interpolation, substeps, jit="auto" if worth else False
        )
        if span == n:
            break
        span = min(n, span * GROWTH)
    reach = horizon([{"length": span, "growth": phi}])
    if reach is None or reach >= data.n_samples:
        return x0, None
    # the stretch's growth, extrapolated, only suggests it: measured over the whole record, in one pass
    passes, rows, w = _passes(_smoothed(model, data, observed), data, observed, interpolation, substeps, jit=False)
    with np.errstate(over="ignore", invalid="ignore"):
        blocks = passes.sensitivities(np.zeros(0), x0[None, :], passes.segments(np.array([0])), w)
        phi = _growth(blocks.end_S, 0, _state_scale(rows, x0[None, :]))
    return x0, (horizon([{"length": data.n_samples, "growth": phi}]) if phi > PHI_STOP else None)


def short_horizons(
    model: IdentifiedModel, data: Trajectory, observed, *, interpolation: str, substeps: int, length: int
) -> np.ndarray:
    """``data`` re-simulated in stretches of ``length`` samples, each from the initial state that best explains
    it: ``(n_samples, n_states)``. The validation of a model on a record it is hypersensitive on, where one
    simulation of the whole record says nothing (a state error outgrows the response within the record)."""
    fitted = _smoothed(model, data, observed)
    passes, guess, w = _passes(fitted, data, observed, interpolation, substeps, jit="auto")
    starts = passes.segment_starts(max(int(length), 8))
    seg = passes.segments(starts)
    it, _ = initial_states(passes, Iterate(np.zeros(0), guess[starts].copy(), seg, w), sweeps=8, rtol=0.0)
    return passes.simulate(np.zeros(0), it.X0, seg)[: data.n_samples]


def _smoothed(model: IdentifiedModel, record: Trajectory, observed) -> IdentifiedModel:
    """``model`` with each sign as the tanh it is fitted with, its widths from ``record`` (and the states it lets be
    reconstructed)."""
    return smooth_model(model, smoothing_widths(model, [record], state_guess(model, [record], tuple(observed))))


def _passes(fitted, record, observed, interpolation, substeps, jit):
    """The passes of one record with the coefficients fixed, its state guess and its noise precisions."""
    param = Parameterisation.of(fitted, free=False)
    layout = Records.of(fitted, [record], tuple(observed), interpolation, int(substeps))
    passes = Passes(param, layout, jit=jit)
    return passes, state_guess(fitted, [record], tuple(observed)), noise_precisions(layout.Y, np.isfinite(layout.Y))


def _fit(model, record, observed, guess, interpolation, substeps, jit) -> tuple[np.ndarray, float]:
    """The initial state fitted to the whole of ``record`` from ``guess`` (kept when the fit is not finite), and
    the growth of a state error over the record."""
    fitted = _smoothed(model, record, observed)
    passes, rows, w = _passes(fitted, record, observed, interpolation, substeps, jit)
    start = Iterate(np.zeros(0), guess[None, :], passes.segments(np.array([0])), w)
    it, _ = initial_states(passes, start, sweeps=SWEEPS, rtol=0.0)
    assert it.blocks is not None  # initial_states returns the iterate with its pass
    phi = _growth(it.blocks.end_S, 0, _state_scale(rows, it.X0))
    return (it.X0[0] if np.all(np.isfinite(it.X0)) else guess), phi
