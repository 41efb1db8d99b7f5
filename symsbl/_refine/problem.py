"""What an output-error fit estimates, and the records it fits: the parameterisation and the data layout.

A model ``x_i' = sum_j c_ij term_ij(x, u)`` is linear in its coefficients. The output-error fit
estimates the coefficients of every equation that is not fixed (kinematic equations ``x' = v`` are
exact; algebraic outputs ``y = sum_j c_j term_j(x, u)`` have equations too) from the *measured* channels,
the model's outputs ``y = h(x, u, theta)`` (:mod:`symsbl._model.outputs`); the states are simulated. The
records are laid end to end, each starting with a reset, with the input of every sample interval at the
integrator's stage nodes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .._base.errors import DataError, expected
from .._data.trajectory import Trajectory
from .._model import IdentifiedModel
from .._model.outputs import Output, StateOutput
from .._simulation.signals import Sampled

__all__ = [
    "Parameterisation",
    "Records",
    "INTERPOLATIONS",
    "check_records",
    "choose_substeps",
    "window_plan",
    "N_WINDOWS",
    "SUBSTEP_TOL",
    "resolve_outputs",
]

#: How a measured input runs between its samples (see :class:`symsbl.Sampled`).
INTERPOLATIONS = ("linear", "cubic", "periodic", "hold")


@dataclass(frozen=True)
class Parameterisation:
    """The model's free coefficients ``theta`` and its right-hand side as a function of them.

    Attributes
    ----------
    model : IdentifiedModel
    terms : tuple of (int, int, bool)
        Per term of the model, in :meth:`IdentifiedModel.parameters` order: equation index, position
        in the equation, and whether its coefficient is free.
    theta0 : ndarray, shape (n_free,)
        The model's coefficients of the free terms.
    names : tuple of str
        ``"state: term"`` of every free coefficient.
    """

    model: IdentifiedModel
    terms: tuple
    theta0: np.ndarray
    names: tuple

    @classmethod
    def of(cls, model: IdentifiedModel, free: bool = True) -> Parameterisation:
        """Every term of every non-fixed equation is free, except coefficients fixed by convention (none with
        ``free=False``: the model as it is)."""
        terms, theta, names = [], [], []
        everything = free
        for i, eq in enumerate(model.equations):
            for j, term in enumerate(eq.terms):
                free = everything and not eq.fixed and not term.fixed
                terms.append((i, j, free))
                if free:
                    theta.append(term.coef)
                    names.append(f"{eq.lhs}: {term.name}")
        return cls(model, tuple(terms), np.array(theta, dtype=float), tuple(names))

    @property
    def n_free(self) -> int:
        """Number of free coefficients."""
        return self.theta0.size

    def rows(self, x: ca.SX, u: ca.SX, theta: ca.SX) -> dict[str, ca.SX]:
        """The right-hand side of every equation (a state's derivative, an algebraic output) by its left-hand
        side, at state ``x``, input ``u`` and free coefficients ``theta``."""
        model = self.model
        rows = [ca.SX(0) for _ in model.equations]
        k = 0
        for i, j, free in self.terms:
            term = model.equations[i].terms[j]
            coef = theta[k] if free else term.coef
            k += int(free)
            rows[i] = rows[i] + coef * term.expr
        f = ca.vertcat(*rows)
        variables = ca.vertcat(*model.states, *model.inputs)
        values = ca.vertcat(x, u) if model.inputs else x
        f = ca.substitute(f, variables, values)
        return {eq.lhs: f[i] for i, eq in enumerate(model.equations)}

    def rhs(self, x: ca.SX, u: ca.SX, theta: ca.SX) -> ca.SX:
        """The right-hand side ``(n_states, 1)`` at state ``x``, input ``u`` and free coefficients ``theta``."""
        rows = self.rows(x, u, theta)
        return ca.vertcat(*[rows[n] for n in self.model.state_names])

    def observe(self, outputs) -> Callable[[ca.SX, ca.SX, ca.SX], ca.SX]:
        """The function ``(x, u, theta) -> y`` of the ``outputs`` (an SX column, one row per output)."""
        names = self.model.state_names

        def h(x: ca.SX, u: ca.SX, theta: ca.SX) -> ca.SX:
            states = {n: x[i] for i, n in enumerate(names)}
            rows = self.rows(x, u, theta) if any(o.state is None for o in outputs) else {}
            return ca.vertcat(*[o.expression(states, rows) for o in outputs])

        return h

    def coefficients(self, theta: np.ndarray) -> list[np.ndarray]:
        """Per equation, its coefficients with the free ones set to ``theta``."""
        out = [eq.coefs.copy() for eq in self.model.equations]
        k = 0
        for i, j, free in self.terms:
            if free:
                out[i][j] = theta[k]
                k += 1
        return out


def _stage_values(traj: Trajectory, names, interpolation: str, substeps: int) -> np.ndarray:
    """The inputs at the ``2 substeps + 1`` stage nodes of every sample interval, ``(n - 1, n_u * nodes)``."""
    n_nodes = 2 * substeps + 1
    if not names:
        return np.zeros((traj.n_samples - 1, 0))
    U = np.column_stack([traj.column(n) for n in names])
    t = traj.t
    vals = Sampled(t, U, kind=interpolation).at_nodes(t, n_nodes)  # (n - 1, nodes, inputs)
    return np.ascontiguousarray(vals.reshape(t.size - 1, n_nodes * len(names)))


@dataclass
class Records:
    """The records of one fit laid end to end.

    Attributes
    ----------
    Y : ndarray, shape (n_total, n_measured)
        Measured states (rows of every record in turn).
    UD : ndarray, shape (n_total, n_u * nodes)
        Row ``r`` holds the input over the interval that *ends* at sample ``r`` (zero at a record's
        first sample, where the state is reset instead of stepped).
    UN : ndarray, shape (n_total, n_u)
        The inputs at each sample (what an output that depends on the input reads).
    DT : ndarray, shape (n_total,)
        The step that ends at each sample (0 at a record's first sample).
    starts, lengths : ndarray of int
        First row and number of samples of each record.
    outputs : tuple of Output
        The measured channels, the columns of ``Y`` (see :mod:`symsbl._model.outputs`).
    state_index : tuple of int or None
        When every channel is a state as it is: their indices among the model's states (else None).
    """

    Y: np.ndarray
    UD: np.ndarray
    DT: np.ndarray
    starts: np.ndarray
    lengths: np.ndarray
    outputs: tuple
    interpolation: str
    substeps: int
    UN: np.ndarray
    state_index: tuple | None = None

    @property
    def n_outputs(self) -> int:
        """Measured channels."""
        return len(self.outputs)

    @property
    def names(self) -> tuple[str, ...]:
        """The measured channels' names (the columns of ``Y``)."""
        return tuple(o.name for o in self.outputs)

    @property
    def row_record(self) -> np.ndarray:
        """The record of every row, ``(n_total,)``."""
        return np.repeat(np.arange(len(self.lengths)), self.lengths)

    @classmethod
    def of(cls, model: IdentifiedModel, records, measured, interpolation: str, substeps: int) -> Records:
        """Lay out ``records`` (Trajectories holding the measured channels and the model's inputs); ``measured``
        are the channels' names or :class:`~symsbl._model.outputs.Output` objects (see :func:`resolve_outputs`)."""
        outputs = resolve_outputs(model, measured)
        names = tuple(o.name for o in outputs)
        n_nodes = 2 * substeps + 1
        lengths = np.array([r.n_samples for r in records])
        starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
        total = int(lengths.sum())
        Y = np.empty((total, len(names)))
        UD = np.zeros((total, n_nodes * len(model.input_names)))
        UN = np.zeros((total, len(model.input_names)))
        DT = np.zeros(total)
        for r, s in zip(records, starts):
            n = r.n_samples
            Y[s : s + n] = np.column_stack([r.column(m) for m in names])
            UD[s + 1 : s + n] = _stage_values(r, model.input_names, interpolation, substeps)
            if model.input_names:
                UN[s : s + n] = np.column_stack([r.column(u) for u in model.input_names])
            DT[s + 1 : s + n] = np.diff(r.t)
        states = model.state_names
        index = tuple(states.index(o.state) for o in outputs) if all(o.state is not None for o in outputs) else None
        return cls(Y, UD, DT, starts, lengths, outputs, interpolation, substeps, UN, index)

    @property
    def n_total(self) -> int:
        """Samples of all records together."""
        return int(self.lengths.sum())


def resolve_outputs(model: IdentifiedModel, measured) -> tuple[Output, ...]:
    """The outputs named ``measured``: the model's outputs of those names (:attr:`IdentifiedModel.observation`),
    a state as it is otherwise; Output objects are taken as they are."""
    by_name = {o.name: o for o in model.observation}
    out = []
    for m in measured:
        if isinstance(m, Output):
            out.append(m)
        elif m in by_name:
            out.append(by_name[m])
        elif m in model.state_names:
            out.append(StateOutput(m))
        else:
            raise DataError(
                expected(
                    "measured",
                    f"outputs of the model {list(by_name)} or its states {list(model.state_names)}",
                    m,
                    raw=False,
                )
            )
    return tuple(out)


def check_records(model: IdentifiedModel, data, measured) -> tuple[list[Trajectory], tuple[str, ...]]:
    """The records as a list and the measured channels (the model's outputs, or states as they are): every record
    must hold those and the model's inputs."""
    records = [data] if isinstance(data, Trajectory) else list(data) if isinstance(data, (list, tuple)) else None
    if not records or not all(isinstance(r, Trajectory) for r in records):
        raise DataError(
            expected("data", "a Trajectory or a non-empty list of Trajectories", type(data).__name__, raw=True)
        )
    available = set(records[0].state_names)
    if measured is None:
        measured = tuple(o.name for o in model.observation if o.name in available)
        if not measured and not model.outputs:  # a model fitted on other channels: its states in this data
            measured = tuple(m for m in model.state_names if m in available)
    measured = tuple(measured)
    allowed = set(model.output_names) | set(model.state_names)
    if not measured or any(m not in allowed for m in measured):
        raise DataError(
            expected(
                "measured", f"outputs of the model {sorted(allowed)} present in the data", list(measured), raw=False
            )
        )
    for k, r in enumerate(records):
        missing = [n for n in list(measured) + list(model.input_names) if n not in r.state_names + r.input_names]
        if missing:
            raise DataError(
                expected(
                    f"data[{k}]",
                    f"the measured channels {list(measured)} and the inputs {list(model.input_names)}",
                    f"a record without {missing}",
                    raw=True,
                )
            )
        if r.n_samples < 4:
            raise DataError(expected(f"data[{k}]", "a record of at least 4 samples", f"{r.n_samples}", raw=True))
    return records, measured


#: Windows a record contributes when the records are longer than the refinement's sample budget.
N_WINDOWS = 4


def window_plan(lengths, max_samples: int) -> tuple[list[tuple[int, int, int]], str]:
    """What to refine on: ``(record, start, stop)`` of every record, or of evenly spaced windows.

    Records totalling more than ``max_samples`` samples contribute :data:`N_WINDOWS` windows each, spread
    from start to end, their lengths in proportion to the record's; each window keeps its own initial
    state in the fit.
    """
    lengths = [int(n) for n in lengths]
    total = sum(lengths)
    if total <= max_samples:
        return [(k, 0, n) for k, n in enumerate(lengths)], f"all {total} samples"
    plan = []
    for k, n in enumerate(lengths):
        share = max(8, int(max_samples * n / total))
        if share >= n:
            plan.append((k, 0, n))
            continue
        width = max(8, share // N_WINDOWS)
        plan += [(k, int(a), int(a) + width) for a in np.linspace(0, n - width, N_WINDOWS).astype(int)]
    used = sum(b - a for _, a, b in plan)
    return plan, (
        f"{used} of {total} samples ({len(plan)} windows spread over the record(s); max_samples={max_samples})"
    )


#: Error of the RK4 simulation accumulated over the system's memory that :func:`choose_substeps` allows,
#: relative to the state's size (0.1 %: a tenth of the held-out errors users read).
SUBSTEP_TOL = 1e-3


def choose_substeps(
    param: Parameterisation, records, guess: np.ndarray, theta: np.ndarray, extra_rate: float = 0.0
) -> int:
    """RK4 steps per sample interval: enough that the simulation's error stays small over the system's memory.

    RK4's local error in a mode ``lambda`` is ``(h |lambda|)^5 / 120`` of the state per step; it accumulates
    over the steps the system remembers, ``min(T, 1 / |Re lambda|) / h`` (``T`` the longest record), so a
    lightly damped oscillator, which remembers for many periods, needs smaller steps than its frequency alone
    asks for: the steps are chosen so that ``(h |lambda|)^4 |lambda| min(T, 1 / |Re lambda|) / 120 <=``
    :data:`SUBSTEP_TOL`, and ``h |lambda| <= 0.25`` in any case. (Measured on a hardening oscillator with 1 s
    of memory at 1 kHz: the step ``h |lambda| = 0.27`` the second rule alone allows re-simulates the true
    model 1.2 % away from the exact response of a 4 s record; the first rule takes two substeps, 0.05 %.)
    The eigenvalues of the right-hand side's Jacobian are taken over up to 256 evenly spaced samples of the
    records and at each state's extremes, where a hardening spring is stiffest (velocities not measured
    at their estimates, latent states as the starting model simulates them). A ``tanh(a / eps)`` that stands
    for ``sign(a)`` adds the stiffness ``|coef| / eps`` (at ``a = 0``).
    """
    model = param.model
    nx = len(model.states)
    x, u = ca.SX.sym("x", nx), ca.SX.sym("u", len(model.inputs))
    th = ca.SX.sym("th", param.n_free)
    jac = ca.Function("rhs_jacobian", [x, u, th], [ca.jacobian(param.rhs(x, u, th), x)])
    worst = 0.0
    offset = 0
    memory = max(float(r.t[-1] - r.t[0]) for r in records)
    for r in records:
        G = guess[offset : offset + r.n_samples]
        offset += r.n_samples
        rows = np.unique(
            np.concatenate(
                [
                    np.linspace(0, r.n_samples - 1, min(256, r.n_samples)).astype(int),
                    np.argmax(G, axis=0),
                    np.argmin(G, axis=0),
                ]
            )
        )
        X = G[rows]
        U = (
            np.column_stack([r.column(n) for n in model.input_names])[rows]
            if model.inputs
            else np.zeros((rows.size, 0))
        )
        J = np.asarray(jac.map(rows.size)(X.T, U.T, np.repeat(theta[:, None], rows.size, 1))).reshape(nx, rows.size, nx)
        ev = np.linalg.eigvals(np.transpose(J, (1, 0, 2))).ravel()  # (samples * nx,)
        ev = ev[np.isfinite(ev) & (np.abs(ev) > 0)]
        if ev.size:
            rate = np.abs(ev)
            remembered = np.minimum(memory, 1.0 / np.maximum(np.abs(ev.real), 1e-300))
            h_max = np.minimum(0.25 / rate, (120.0 * SUBSTEP_TOL / (rate * remembered)) ** 0.25 / rate)
            worst = max(worst, float(np.max(r.dt / h_max)))
    dt = max(r.dt for r in records)
    return int(min(32, max(1, math.ceil(worst - 1e-9), math.ceil(dt * extra_rate))))
