"""The MR damper example's pieces: the record, the published model, the hidden-state start, the fit, the score.

See ``mr_damper.py`` for the model and its arguments; this module is what that script runs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
from _csvrows import column, number, read_rows  # beside this module

import symsbl
from symsbl import AlgebraicOutput, Equation, IdentifiedModel, TermEstimate

#: Columns a record must hold: displacement (cm), velocity (cm/s), voltage (V), force (N).
COLUMNS = ("D", "V", "Y", "F")
#: RK4 steps per sample at least (the published model's states turn at up to 2e4 1/s: 0.2 of a step at 3 kHz).
SUBSTEPS = 32
#: The largest ``h |lambda|`` of an RK4 step: a hysteretic state saturating at a displacement ``a`` turns at
#: ``2 |V| / a`` (1e5 1/s for 10 um at 50 cm/s), and RK4 is stable up to 2.78.
STEP = 1.0
#: The voltage filter's rate (1/s) and the hysteretic state's saturation (cm) the start tries.
RATES = (50.0, 100.0, 200.0, 400.0)
YIELDS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05)
#: The active span (the damper moving) cut for fitting, choosing the number of hidden states, and the test.
SPANS = {"fit": (0.0, 0.6), "choice": (0.6, 0.75), "test": (0.75, 1.0)}

D, V, Y = symsbl.symbols("D V Y")
U = ca.SX.sym("u")  # the filtered voltage: the current driver and the coil's field lag the command


@dataclass(frozen=True)
class Record:
    """One damper record: displacement D (cm), velocity V (cm/s), voltage Y (V), force F (N), rate fs (Hz)."""

    D: np.ndarray
    V: np.ndarray
    Y: np.ndarray
    F: np.ndarray
    fs: float

    @property
    def t(self) -> np.ndarray:
        return np.arange(self.F.size) / self.fs

    @property
    def inputs(self) -> np.ndarray:
        return np.column_stack([self.D, self.V, self.Y])

    def part(self, stop: int) -> Record:
        """The record's first ``stop`` samples."""
        return Record(self.D[:stop], self.V[:stop], self.Y[:stop], self.F[:stop], self.fs)


def read_record(path: Path) -> Record:
    """A record in the layout of ``shared/data/MRDamper`` (columns t, D, V, Y, F; fs on the first row or t)."""
    rows, lines = read_rows(path)
    if len(rows) < 100:
        raise ValueError(f"{len(rows)} rows, where a record holds 100 samples or more")
    missing = [name for name in COLUMNS if name not in rows[0]]
    if missing:
        raise ValueError(f"no column {', '.join(missing)} (the columns are {', '.join(rows[0])})")
    at = next((k for k, r in enumerate(rows) if r.get("fs")), None)  # the rate may be given in the first row only
    if at is not None:
        fs = number(rows[at]["fs"], lines[at], "fs")
    elif "t" in rows[0]:
        t = column(rows, lines, "t")
        if not np.all(np.diff(t) > 0):
            raise ValueError("the times t do not increase: they give no sampling rate (add a column fs)")
        fs = (t.size - 1) / (t[-1] - t[0])
    else:
        raise ValueError("no column fs or t to give the sampling rate (add one)")
    return Record(*(column(rows, lines, name) for name in COLUMNS), fs=float(fs))


def active_end(rec: Record) -> int:
    """The sample after which the damper rests (its velocity's 0.1 s RMS below 5 % of its spread)."""
    window = max(int(0.1 * rec.fs), 1)
    moving = np.sqrt(np.convolve(rec.V**2, np.ones(window) / window, mode="same")) > 0.05 * rec.V.std()
    return int(np.flatnonzero(moving)[-1]) + 1 if moving.any() else rec.F.size


def spans(rec: Record) -> dict[str, slice]:
    """The fit, choice and test spans of the record's active part (:data:`SPANS`)."""
    end = active_end(rec)
    return {name: slice(int(lo * end), int(hi * end)) for name, (lo, hi) in SPANS.items()}


# -- the published model -------------------------------------------------------------------------

#: Spencer, Dyke, Sain and Carlson (1997), in N, cm, s, V (``shared/data/MRDamper/README.md``).
SPENCER = dict(
    c0a=21.0, c0b=3.50, k0=46.9, c1a=283.0, c1b=2.95, k1=5.00, x0=14.3, alpha_a=140.0, alpha_b=695.0,
    gamma=363.0, beta=363.0, A=301.0, n=2, eta=190.0,
)  # fmt: skip


def spencer(p: dict = SPENCER) -> symsbl.OdeSystem:
    """The published modified Bouc-Wen model: states y (the internal displacement), z, u; force output F."""
    y, z, u = symsbl.symbols("y z u")
    alpha, c0, c1 = p["alpha_a"] + p["alpha_b"] * u, p["c0a"] + p["c0b"] * u, p["c1a"] + p["c1b"] * u
    dy = (alpha * z + c0 * V + p["k0"] * (D - y)) / (c0 + c1)
    r = V - dy
    dz = -p["gamma"] * ca.fabs(r) * z * ca.fabs(z) ** (p["n"] - 1) - p["beta"] * r * ca.fabs(z) ** p["n"] + p["A"] * r
    system = symsbl.OdeSystem((y, z, u), (D, V, Y), (dy, dz, -p["eta"] * (u - Y)), name="spencer")
    return system.with_outputs(F=c1 * dy + p["k1"] * (D - p["x0"]))


def spencer_force(rec: Record) -> np.ndarray:
    """The published model's force, simulated free-run from the measured inputs (y = D, z = 0, u = Y at t = 0)."""
    run = symsbl.simulate(
        spencer(), rec.t, inputs=_inputs(rec), x0=[rec.D[0], 0.0, rec.Y[0]], method="rk4", substeps=SUBSTEPS
    )
    return run.states[:, run.state_names.index("F")]


# -- the identified model ------------------------------------------------------------------------


def _inputs(rec: Record) -> symsbl.Sampled:
    return symsbl.Sampled(rec.t, rec.inputs, kind="cubic")


def hidden_symbols(n: int) -> list[ca.SX]:
    return [ca.SX.sym(f"z{i + 1}") for i in range(n)]


def law_terms(z: ca.SX) -> list[ca.SX]:
    """The hysteretic law ``z' = V - (g + h u) |V| z |z| - b V z^2`` (Bouc-Wen of exponent 2), its input term
    first."""
    return [V, ca.fabs(V) * z * ca.fabs(z), U * ca.fabs(V) * z * ca.fabs(z), V * z**2]


def force_terms(zs: list[ca.SX]) -> list[ca.SX]:
    """The force's library: a constant, a spring, a viscous and a quadratic damper (both also times the filtered
    voltage), the filtered voltage, and each hidden state alone and times the filtered voltage."""
    base = [ca.SX(1), D, V, V * ca.fabs(V), U, U * V, U * V * ca.fabs(V)]
    return base + [e for z in zs for e in (z, U * z)]


def _term(expr, coef: float, fixed: bool = False) -> TermEstimate:
    return TermEstimate(expr, float(coef), 0.0, fixed=fixed)


def _equation(lhs: str, terms: list[TermEstimate], algebraic: bool = False) -> Equation:
    return Equation(lhs, tuple(terms), np.zeros((len(terms),) * 2), 0.0, 0.0, algebraic=algebraic)


def damper_model(rate: float, laws: list[tuple[float, ...]], force: np.ndarray) -> IdentifiedModel:
    """The model of the voltage filter's ``rate``, the hidden states' laws (the coefficients of
    :func:`law_terms` after the first) and the force's coefficients (of :func:`force_terms`)."""
    zs = hidden_symbols(len(laws))
    equations = [_equation("u", [_term(Y - U, rate)])]
    for z, coefs in zip(zs, laws):
        first, *rest = law_terms(z)  # the scale of z: its input term's coefficient is 1 (z in cm)
        terms = [_term(first, 1.0, fixed=True)] + [_term(e, c) for e, c in zip(rest, coefs)]
        equations.append(_equation(z.name(), terms))
    equations.append(_equation("F", [_term(e, c) for e, c in zip(force_terms(zs), force)], algebraic=True))
    return IdentifiedModel(
        (U, *zs),
        (D, V, Y),
        tuple(equations),
        measured=(),
        outputs=(AlgebraicOutput("F"),),
        metadata={"example": "mr_damper", "hidden_states": len(laws)},
    )


def _columns(exprs: list[ca.SX], symbols: list[ca.SX], values: list[np.ndarray]) -> np.ndarray:
    """The expressions evaluated on the samples (one column each)."""
    f = ca.Function("columns", symbols, [ca.vertcat(*exprs)])
    return np.array(f(*[np.asarray(v)[None, :] for v in values])).T


def substeps(rec: Record, stiffness: float) -> int:
    """RK4 steps per sample for hysteretic states of ``stiffness`` ``max sqrt(g + h u)`` (1/cm) on ``rec``."""
    return max(SUBSTEPS, math.ceil(2 * np.max(np.abs(rec.V)) * stiffness / rec.fs / STEP))


def laws(model: IdentifiedModel) -> list[tuple[float, float, float]]:
    """The coefficients ``(c1, c2, c3)`` of each hysteretic law ``z' = V + (c1 + c2 u) |V| z |z| + c3 V z^2``."""
    names = {z.name() for z in hidden_symbols(model.metadata["hidden_states"])}
    return [tuple(t.coef for t in eq.terms[1:4]) for eq in model.equations if eq.lhs in names]


def stiffness(model: IdentifiedModel, rec: Record) -> float:
    """The largest ``sqrt(|c1 + c2 u| + |c3|)`` of the model's hysteretic laws over the record's voltages."""
    worst = [abs(c1 + c2 * y) + abs(c3) for c1, c2, c3 in laws(model) for y in (rec.Y.min(), rec.Y.max())]
    return math.sqrt(max(worst, default=0.0))


def bounded_voltages(model: IdentifiedModel) -> tuple[float, float]:
    """The filtered voltages over which every hysteretic law saturates: ``c1 + c2 u < -max(0, c3)``.

    Loading (``V z > 0``), ``z' = V (1 + (c1 + c2 u + c3) z^2)`` saturates where ``c1 + c2 u + c3 < 0``; unloading
    from there, ``z' = V (1 - (c1 + c2 u - c3) z^2)`` keeps the sign of ``V`` (z returns) where ``c1 + c2 u < 0``.
    """
    low, high = -np.inf, np.inf
    for c1, c2, c3 in laws(model):
        edge = (-max(0.0, c3) - c1) / c2 if c2 else (np.inf if c1 < -max(0.0, c3) else -np.inf)
        low, high = (max(low, edge), high) if c2 < 0 else (low, min(high, edge))
    return float(low), float(high)


def _simulate_law(rhs, state: ca.SX, drive: ca.SX, rec: Record, signal: np.ndarray, x0: float, steps: int):
    system = symsbl.OdeSystem((state,), (drive,), (rhs,), name=state.name())
    drive_signal = symsbl.Sampled(rec.t, signal, kind="cubic")  # as the model's inputs run (:func:`force`)
    return symsbl.simulate(system, rec.t, inputs=drive_signal, x0=[x0], method="rk4", substeps=steps).states[:, 0]


def start(rec: Record, n_hidden: int) -> tuple[IdentifiedModel, dict]:
    """A starting model with ``n_hidden`` hysteretic states: each candidate law simulated from the measured
    velocity, the force regressed on its library given them (linear: the states are then known), the law
    of least residual added one state at a time. Returns the model and the start's trajectories (by state)."""
    filtered = {r: _simulate_law(r * (Y - U), U, Y, rec, rec.Y, rec.Y[0], SUBSTEPS) for r in RATES}
    z = hidden_symbols(1)[0]
    hidden = {
        a: _simulate_law(V - ca.fabs(V) * z * ca.fabs(z) / a**2, z, V, rec, rec.V, 0.0, substeps(rec, 1 / a))
        for a in YIELDS
    }

    def fit(rate, chosen):
        zs = hidden_symbols(len(chosen))
        X = _columns(force_terms(zs), [D, V, U, *zs], [rec.D, rec.V, filtered[rate]] + [hidden[a] for a in chosen])
        coef, *_ = np.linalg.lstsq(X, rec.F, rcond=None)
        return float(np.sum((X @ coef - rec.F) ** 2)), coef

    chosen: list[float] = []
    rate = min(RATES, key=lambda r: fit(r, [])[0])
    for _ in range(n_hidden):
        _, rate, best = min((fit(r, [*chosen, a])[0], r, a) for r in RATES for a in YIELDS if a not in chosen)
        chosen.append(best)
    model = damper_model(rate, [(-1 / a**2, 0.0, 0.0) for a in chosen], fit(rate, chosen)[1])  # h, b found by the fit
    guesses = {"u": filtered[rate], **{f"z{i + 1}": hidden[a] for i, a in enumerate(chosen)}}
    return model, guesses


def identify(rec: Record, n_hidden: int) -> IdentifiedModel:
    """The model with ``n_hidden`` hysteretic states fitted to ``rec`` by output error, every term kept."""
    model, guesses = start(rec, n_hidden)
    columns = ["F", *guesses]  # the states' start trajectories seed the output error's
    states = np.column_stack([rec.F, *guesses.values()])
    record = symsbl.Trajectory(rec.t, states, rec.inputs, tuple(columns), ("D", "V", "Y"))
    steps = substeps(rec, stiffness(model, rec))
    options = symsbl.RefineOptions(select=False, noise="white", doubts="report", substeps=steps)
    return symsbl.refine(model, record, measured=["F"], options=options)


def force(model: IdentifiedModel, rec: Record) -> np.ndarray:
    """The model's force, simulated free-run from the measured inputs (u = Y, hidden states 0 at t = 0)."""
    x0 = [rec.Y[0]] + [0.0] * (len(model.states) - 1)
    steps = substeps(rec, stiffness(model, rec))
    run = symsbl.simulate(model.to_system(), rec.t, inputs=_inputs(rec), x0=x0, method="rk4", substeps=steps)
    return run.states[:, run.state_names.index("F")]


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))
