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

from .._model import IdentifiedModel
from .._trajectory import Trajectory
from .engine import _smoothing_widths, smooth_model
from .problem import Parameterisation, Records
from .sensitivity import Passes
from .solver import initial_states, noise_precisions

__all__ = ["initial_state"]


def initial_state(model: IdentifiedModel, data: Trajectory, observed, guess: np.ndarray, *, interpolation: str,
                  substeps: int, length: int) -> np.ndarray:
    """The state at ``data``'s first sample that best explains its first ``length`` samples.

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
    record = data.slice(0, max(8, min(int(length), data.n_samples)))
    fitted = smooth_model(model, _smoothing_widths(model, [record]))
    param = Parameterisation.of(fitted, free=False)
    layout = Records.of(fitted, [record], tuple(observed), interpolation, int(substeps))
    passes = Passes(param, layout, jit="auto")
    passes.use_weights(noise_precisions(layout.Y, np.isfinite(layout.Y)))
    passes.use_segments(np.array([0]))
    X0 = initial_states(passes, np.zeros(0), np.asarray(guess, dtype=float)[None, :], sweeps=8)
    return X0[0] if np.all(np.isfinite(X0)) else np.asarray(guess, dtype=float)
