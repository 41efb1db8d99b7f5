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
    columns of ``G`` and the inputs at the record's: RK4 with the drive linear between samples, at
    :data:`GUESS_SUBSTEPS` in turn until the run stays finite; zeros if none does."""
    known = [k for k in range(len(model.states)) if k not in missing]
    drive = ca.vertcat(*[model.states[k] for k in known], *model.inputs)
    x = ca.vertcat(*[model.states[k] for k in missing])
    rows = {eq.lhs: sum((t.coef * t.expr for t in eq.terms), ca.SX(0)) for eq in model.equations if not eq.algebraic}
    rhs = ca.Function("latent_rhs", [x, drive], [ca.vertcat(*[rows[model.state_names[k]] for k in missing])])
    U = np.column_stack([record.column(n) for n in model.input_names]) if model.inputs else np.zeros((len(G), 0))
    W = np.column_stack([G[:, known], U])
    W = np.vstack([W[:-1].T, W[1:].T])  # each interval's drive at its two ends
    for substeps in GUESS_SUBSTEPS:
        X = np.asarray(_stepper(rhs, x.numel(), drive.numel(), record.dt, substeps).mapaccum(W.shape[1])(0.0, W))
        if np.all(np.isfinite(X)):  # RK4 past its stability limit grows without bound within a few steps
            return np.vstack([np.zeros((1, len(missing))), X.T])
    return np.zeros((len(G), len(missing)))


def _stepper(rhs: ca.Function, nx: int, nw: int, dt: float, substeps: int) -> ca.Function:
    """One sample interval of RK4 in ``substeps`` steps, the drive linear between its values at the two ends."""
    x0, ends = ca.SX.sym("x0", nx), ca.SX.sym("w", 2 * nw)
    h = dt / substeps

    def w(s):
        return (1 - s) * ends[:nw] + s * ends[nw:]

    x = x0
    for i in range(substeps):
        s = i / substeps
        k1 = rhs(x, w(s))
        k2 = rhs(x + h / 2 * k1, w(s + 0.5 / substeps))
        k3 = rhs(x + h / 2 * k2, w(s + 0.5 / substeps))
        k4 = rhs(x + h * k3, w(s + 1 / substeps))
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("latent_step", [x0, ends], [x])


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
