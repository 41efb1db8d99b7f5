"""The records of a refinement as rows of states and inputs: the state guess every fit starts from, and the
rows on which candidate terms are compared.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .._derivatives.kinematics import estimate_velocity
from .._model import IdentifiedModel

__all__ = ["state_guess", "design_rows", "term_values"]


def state_guess(model: IdentifiedModel, records, measured) -> np.ndarray:
    """Every state at every sample of ``records`` laid end to end: measured values (or a column given as a
    guess), velocities from their positions, zeros."""
    position_of = {v: x for x, v in model.kinematics}
    rows = []
    for r in records:
        G = np.zeros((r.n_samples, len(model.states)))
        for k, name in enumerate(model.state_names):
            if name in measured or name in r.state_names:  # a column not measured: a guess only
                G[:, k] = r.column(name)
            elif name in position_of and position_of[name] in measured:
                G[:, k] = estimate_velocity(r.t, r.column(position_of[name]))
        rows.append(G)
    return np.vstack(rows)


def design_rows(model: IdentifiedModel, records, guess: np.ndarray, most: int = 20000) -> np.ndarray:
    """Rows ``(states, inputs)`` of ``guess`` and the records' inputs, evenly thinned to at most ``most``."""
    U = [np.column_stack([r.column(n) for n in model.input_names]) if model.input_names
         else np.zeros((r.n_samples, 0)) for r in records]
    Z = np.column_stack([guess, np.vstack(U)])
    return Z[:: max(1, len(Z) // most)]


def term_values(exprs, model: IdentifiedModel, Z: np.ndarray) -> np.ndarray:
    """Each term evaluated on the rows of ``Z`` (states then inputs), ``(n_rows, n_terms)``."""
    z = ca.vertcat(*model.states, *model.inputs)
    f = ca.Function("terms", [z], [ca.vertcat(*exprs)])
    return np.asarray(f.map(Z.shape[0])(Z.T)).T
