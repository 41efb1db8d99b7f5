"""The records of a refinement as rows of states and inputs: the state guess every fit starts from, and the
rows on which candidate terms are compared.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .._base.casadi import run_chunks
from .._derivatives.kinematics import completed_columns
from .._model import IdentifiedModel
from .problem import resolve_outputs

__all__ = ["state_guess", "design_rows", "term_values"]


def state_guess(model: IdentifiedModel, records, measured) -> np.ndarray:
    """Every state at every sample of ``records`` laid end to end: the records' columns of the states (a column
    of a state that is not measured is a guess only), the members of each kinematic pair reconstructed from the
    measured ones (a velocity from its position, a position or velocity from an acceleration), zeros.
    ``measured``: the channels (names or outputs) fitted."""
    outputs = resolve_outputs(model, measured)
    acceleration = {o.equation: o.name for o in outputs if o.kind == "acceleration"}
    triples = [(x, v, acceleration.get(v)) for x, v in model.kinematics]
    rows = []
    for r in records:
        G = np.zeros((r.n_samples, len(model.states)))
        columns = completed_columns(r, model.state_names, triples)
        for k, name in enumerate(model.state_names):
            if name in columns:
                G[:, k] = columns[name]
        rows.append(G)
    return np.vstack(rows)


def design_rows(model: IdentifiedModel, records, guess: np.ndarray, most: int = 20000) -> np.ndarray:
    """Rows ``(states, inputs)`` of ``guess`` and the records' inputs, evenly thinned to at most ``most``."""
    U = [
        np.column_stack([r.column(n) for n in model.input_names]) if model.input_names else np.zeros((r.n_samples, 0))
        for r in records
    ]
    Z = np.column_stack([guess, np.vstack(U)])
    return Z[:: max(1, len(Z) // most)]


def term_values(exprs, model: IdentifiedModel, Z: np.ndarray) -> np.ndarray:
    """Each term evaluated on the rows of ``Z`` (states then inputs), ``(n_rows, n_terms)``."""
    z = ca.vertcat(*model.states, *model.inputs)
    f = ca.Function("terms", [z], [ca.vertcat(*exprs)])
    n = Z.shape[0]
    out = np.empty((n, len(exprs)))
    if n and len(exprs):  # written in place chunk by chunk: a DM of every value costs more than the terms
        chunk = min(n, CHUNK)
        run_chunks(f.map(chunk), chunk, [np.ascontiguousarray(Z, dtype=float)], [out])
    return out


#: Rows per call of :func:`term_values`.
CHUNK = 4096
