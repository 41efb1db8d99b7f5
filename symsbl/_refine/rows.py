"""The records of a refinement as rows of states and inputs: the state guess every fit starts from, and the
rows on which candidate terms are compared.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .._base.casadi import run_chunks
from .._derivatives.kinematics import completed_columns
from .._model import IdentifiedModel
from .._model.outputs import latent_of
from .._simulation.ode import OdeSystem
from .._simulation.rk4 import run_rk4
from .._simulation.signals import Sampled
from .problem import resolve_outputs

__all__ = ["state_guess", "simulated_guess", "design_rows", "term_values"]

#: RK4 steps per sample tried in turn when the states no column holds are simulated for the choice of substeps,
#: on each record's first GUESS_SAMPLES samples.
GUESS_SUBSTEPS = (4, 16, 64, 256)
GUESS_SAMPLES = 2**14


def state_guess(model: IdentifiedModel, records, measured) -> np.ndarray:
    """Every state at every sample of ``records`` laid end to end: the records' columns of the states (a column
    of a state that is not measured is a guess only), the members of each kinematic pair reconstructed from the
    measured ones (a velocity from its position, a position or velocity from an acceleration), zeros.
    ``measured``: the channels (names or outputs) fitted."""
    triples = _triples(model, measured)
    rows = []
    for r in records:
        G = np.zeros((r.n_samples, len(model.states)))
        columns = completed_columns(r, model.state_names, triples)
        for k, name in enumerate(model.state_names):
            if name in columns:
                G[:, k] = columns[name]
        rows.append(G)
    return np.vstack(rows)


def _triples(model: IdentifiedModel, measured) -> list[tuple]:
    """The kinematic triples ``(x, v, a)`` of ``model``, ``a`` the column of an accelerometer on ``v`` (or None)."""
    acceleration = {o.equation: o.name for o in resolve_outputs(model, measured) if o.kind == "acceleration"}
    return [(x, v, acceleration.get(v)) for x, v in model.kinematics]


def simulated_guess(model: IdentifiedModel, records, measured, guess: np.ndarray) -> tuple[list, np.ndarray] | None:
    """Each record's first :data:`GUESS_SAMPLES` samples and the guess on them with the states no column holds
    simulated by the starting model (None when every state has a column): zeros, the guess of those states,
    hide a stiffness the choice of substeps must see (a hysteretic state turns fastest where it saturates)."""
    if not latent_of(model.state_names, resolve_outputs(model, measured), model.kinematics):
        return None  # every state is read by a fitted channel or reconstructed from one
    triples = _triples(model, measured)
    parts, rows, offset, simulated = [], [], 0, False
    for r in records:
        part = r.slice(0, GUESS_SAMPLES)
        G = guess[offset : offset + part.n_samples].copy()
        offset += r.n_samples
        have = completed_columns(part, model.state_names, triples)
        missing = [k for k, name in enumerate(model.state_names) if name not in have]
        if missing:
            G[:, missing] = _simulated(model, part, G, missing)
            simulated = True
        parts.append(part)
        rows.append(G)
    return (parts, np.vstack(rows)) if simulated else None


def _simulated(model: IdentifiedModel, record, G: np.ndarray, missing: list[int]) -> np.ndarray:
    """The states ``missing`` simulated from zero by the model's own equations, the other states held at their
    columns of ``G`` and the inputs at the record's (both linear between samples): fixed-step RK4 at
    :data:`GUESS_SUBSTEPS` in turn until the run stays finite; zeros if none does."""
    known = [k for k in range(len(model.states)) if k not in missing]
    full = model.to_system()
    system = OdeSystem(
        states=tuple(model.states[k] for k in missing),
        inputs=tuple(model.states[k] for k in known) + tuple(model.inputs),
        rhs=tuple(full.rhs[k] for k in missing),
        parameters=full.parameters,
        parameter_values=full.parameter_values,
        name="latent states",
    )
    U = np.column_stack([record.column(n) for n in model.input_names]) if model.inputs else np.zeros((len(G), 0))
    drive = [Sampled(record.t, np.column_stack([G[:, known], U]))]
    for substeps in GUESS_SUBSTEPS:  # RK4 past its stability limit grows without bound within a few steps
        X, failed, _ = run_rk4(
            system,
            record.t,
            drive,
            np.zeros(len(missing)),
            rtol=None,
            atol=None,
            substeps=substeps,
            chunk_size=4096,
            jit=False,
            options=None,
        )
        if failed is None:
            return X
    return np.zeros((len(G), len(missing)))


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
