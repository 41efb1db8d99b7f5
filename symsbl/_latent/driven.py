"""A latent state driven by a measured signal: candidate laws simulated, the measured equations regressed on them.

Where no mechanical skeleton hosts the latent state (a level, a pressure, a temperature: the upper tank
of a cascade whose lower level alone is measured), its law is looked for among

    z' = d - a phi(z),

``d`` a measured signal (an input, else a measured state) or a library term of one (the outflow
``sqrt(x1)`` of a tank above) and ``phi`` a library term of ``z`` alone, ``a`` on a grid of rates. The
coefficient of ``d`` is held at 1, the scale convention the model prints: a latent state is known up to a
scale that the terms it enters absorb (``sqrt(s z) = sqrt(s) sqrt(z)``), so ``z`` is the level in the units
of ``d`` times time. Each candidate is simulated from the measured ``d`` alone, from its stable equilibrium
at the mean of ``d``, and the measured equations are regressed by the relevance vector machine on the
library with the simulated ``z`` as one more column; a candidate scores the sum of their log evidences (the
rows of the first :data:`SETTLE` of the record left out: the start's transient). The best candidate of each
(drive, law) near the best (:func:`leaders`) starts an output-error refinement (:func:`symsbl.refine`) of
every coefficient, ``a`` and the law's terms with them, beside the "nothing hidden" model of the measured
states alone.

Measured on two tanks in cascade (``x1' = -0.5 sqrt(x1) + 0.4 u``, ``x2' = 0.5 sqrt(x1) - 0.4 sqrt(x2)``,
``x2`` alone measured, 0.5 % noise, 600 s at 5 Hz; library: degree-2 polynomials, ``sqrt`` of both levels
and ``u``): of 180 candidates, ``phi = sqrt(z)`` by ``u`` at ``a = 0.79`` (true 0.5/sqrt(0.4) = 0.79) scored
204 nats above the next (a linear law), and the output error from it left every coefficient within 0.1 %, in
4 s of CPU.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import casadi as ca
import numpy as np
import sympy as sp

from .._base.errors import DataError, SimulationError, expected
from .._data.trajectory import Trajectory
from .._model import Equation, IdentifiedModel, TermEstimate
from .._regression.fit import fit_stats
from .._regression.rows import regression_stats
from .._regression.support import fit_rvm
from .._symbolic.library import Library, Term
from .law import homogeneous_terms

__all__ = [
    "Candidate",
    "laws",
    "leaders",
    "guesses",
    "with_latent",
    "regress",
    "LEADERS",
    "SCREEN_NATS",
    "equilibria",
    "trajectories",
    "screen",
    "start_model",
    "SETTLE",
]

#: Share of the record at its start whose rows the screen leaves out: a candidate starts from its equilibrium at
#: the mean drive, not at the record's own start, and the difference decays over a few time constants.
SETTLE = 0.2
#: The time constants a candidate's rate is chosen for, at the mean drive: from two samples to a quarter of the
#: record (slower than that, the record cannot tell the law from a drift), :data:`RATES` of them.
RATES = 16
#: Candidates refined by output error: the best of each (drive, law), this many at most. The screen's equation
#: error ranks them on a noisy derivative: on the tank cascade at 2 % noise the true law ranked third, 16 nats
#: behind a linear law, and the output error from each of the three u-driven starts found it.
LEADERS = 6
#: Candidates further than this below the best screened are not refined: at 0.5 % noise the true law of the tank
#: cascade led by 204 nats; at 2 % four leaders spread over 38 nats (each output-error fit took 5-12 s there).
SCREEN_NATS = 50.0
#: RK4 steps per sample of the candidates' simulation: a candidate's own time constant is two samples at least.
SUBSTEPS = 2


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One screened law ``z' = d - rate phi(z)`` and its score.

    Attributes
    ----------
    drive : Term
        The measured signal ``d``: a measured state or input, or a homogeneous library term of one (``sqrt(x1)``,
        the outflow of a tank above).
    law : Term
        ``phi(z)``.
    rate : float
        ``a``.
    tau : float
        The law's time constant at its equilibrium at the mean drive (s).
    score : float
        The measured equations' summed log evidence with ``z`` simulated (nats).
    """

    drive: Term
    law: Term
    rate: float
    tau: float
    score: float

    def to_json(self) -> dict:
        """The candidate as ``metadata["latent"]`` records it."""
        return {"drive": self.drive.name, "law": self.law.name, "rate": self.rate, "tau": self.tau, "score": self.score}


def laws(library: Library, latent: str, signals) -> tuple[list, list]:
    """The candidate drives and laws, homogeneous terms of one variable each (``z``, ``sqrt(z)``, ``z|z|``, ...;
    ``z``'s scale is a convention, so ``sin(z)`` would be an accident of units): the drives, each measured
    ``signal`` (inputs first) and the library's terms of it alone; the laws, the library's terms of ``latent``
    alone, ``z`` itself always among them."""
    symbols = {s.name(): s for s in library.variables}

    def of(name: str) -> list:
        terms = homogeneous_terms(library.terms, {name}, exclude={"1", name}, fractional=True)
        return [Term(symbols[name]), *terms]

    return [t for n in signals if n in symbols for t in of(n)], of(latent)


def _function(term: Term):
    """A term of one variable as a numpy function of an array."""
    (symbol,) = term.sympy.free_symbols
    f = sp.lambdify(symbol, term.sympy, "numpy")
    return lambda values: np.broadcast_to(f(values), np.shape(values)).astype(float)


def _values(term: Term, record: Trajectory) -> np.ndarray:
    """A term of one variable at every sample of ``record``."""
    (symbol,) = term.sympy.free_symbols
    with np.errstate(all="ignore"):
        return _function(term)(record.column(symbol.name))


def _numeric(term: Term):
    """``phi`` as a numpy function of an array, and ``phi'`` of a number (CasADi's derivative: a sign's is zero,
    where sympy's is a Dirac delta)."""
    (z,) = ca.symvar(term.expr)
    df = ca.Function("slope", [z], [ca.jacobian(term.expr, z)])
    return _function(term), (lambda value: float(df(value)))


#: Where equilibria are looked for: zero and magnitudes from 1e-8 to 1e8 of either sign.
_GRID = np.concatenate([-np.logspace(8, -8, 321), [0.0], np.logspace(-8, 8, 321)])


def equilibria(term: Term, rates: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """For each rate ``a``, the stable equilibrium of ``z' = level - a phi(z)`` nearest zero and the law's slope
    ``a phi'(z)`` there (its inverse time constant); NaN where there is none."""
    phi, dphi = _numeric(term)
    values, slopes = np.full(rates.size, np.nan), np.full(rates.size, np.nan)
    with np.errstate(all="ignore"):
        base = phi(_GRID)
        for k, a in enumerate(rates):
            r = a * base - level
            ok = np.isfinite(r)
            cross = np.flatnonzero(ok[:-1] & ok[1:] & (np.sign(r[:-1]) != np.sign(r[1:])))
            found = [_bisect(lambda z, a=a: a * phi(z) - level, _GRID[j], _GRID[j + 1]) for j in cross]
            stable = [(abs(z), z, a * dphi(z)) for z in found]
            stable = [s for s in stable if math.isfinite(s[2]) and s[2] > 0]
            if stable:
                _, values[k], slopes[k] = min(stable)
    return values, slopes


def _bisect(f, lo: float, hi: float) -> float:
    """The root of ``f`` between ``lo`` and ``hi``, where its sign changes."""
    flo = np.sign(f(lo))
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if np.sign(f(mid)) == flo:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def trajectories(term: Term, drive: np.ndarray, rates: np.ndarray, z0: np.ndarray, dt: float) -> np.ndarray:
    """``z' = drive - a phi(z)`` for every rate at once by RK4, the drive linear between samples:
    ``(n_samples, n_rates)``; a candidate that leaves the law's domain turns NaN. One CasADi loop over the samples
    (``mapaccum``): a Python loop over them costs about 2 s per 10^4 samples and (drive, law)."""
    start = np.atleast_1d(np.asarray(z0, dtype=float))
    if drive.size < 2:
        return start[None, :]
    run = _stepper(term, np.asarray(rates, dtype=float), dt).mapaccum("run", drive.size - 1)
    ends = np.vstack([drive[:-1], drive[1:]])
    return np.vstack([start[None, :], np.asarray(run(start, ends)).T])


def _stepper(term: Term, rates: np.ndarray, dt: float) -> ca.Function:
    """One sample of :func:`trajectories`: ``(z, [d[i], d[i+1]]) -> z`` by :data:`SUBSTEPS` RK4 steps."""
    (symbol,) = ca.symvar(term.expr)
    phi = ca.Function("phi", [symbol], [term.expr])
    z = ca.SX.sym("z", rates.size)
    ends = ca.SX.sym("d", 2)
    h = dt / SUBSTEPS

    def f(w, d):
        return d - ca.DM(rates) * ca.vertcat(*[phi(w[k]) for k in range(rates.size)])

    w = z
    for s in range(SUBSTEPS):
        da, dm, db = (ends[0] + (s + r) / SUBSTEPS * (ends[1] - ends[0]) for r in (0.0, 0.5, 1.0))
        k1 = f(w, da)
        k2 = f(w + 0.5 * h * k1, dm)
        k3 = f(w + 0.5 * h * k2, dm)
        k4 = f(w + h * k3, db)
        w = w + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("step", [z, ends], [w])


def _rates(term: Term, level: float, dt: float, span: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:data:`RATES` rates whose time constants at ``level`` spread evenly (in log) over two samples to a quarter
    of the record, their equilibria and time constants."""
    a = np.logspace(-8, 8, 161)
    z, slope = equilibria(term, a, level)
    tau = 1.0 / slope
    keep = np.flatnonzero(np.isfinite(tau) & (tau >= 2 * dt) & (tau <= span / 4))
    if keep.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    pick = np.unique(np.round(np.linspace(0, keep.size - 1, min(RATES, keep.size))).astype(int))
    keep = keep[pick]
    return a[keep], z[keep], tau[keep]


def screen(record: Trajectory, library: Library, states, latent: str, pairs, fitting) -> list:
    """Every candidate law's score on ``record``, best first; ``states``: the model's states in order."""
    measured = [n for n in states if n != latent]
    drives, phis = laws(library, latent, [*record.input_names, *measured])
    cut = int(SETTLE * record.n_samples)
    settled = record.slice(cut).with_states(measured)  # the rows every candidate is scored on
    found = []
    for drive in drives:
        d = _values(drive, record)
        if not np.all(np.isfinite(d)):
            continue
        for term in phis:
            rates, z0, taus = _rates(term, float(np.mean(d)), record.dt, record.t[-1] - record.t[0])
            if not rates.size:
                continue
            Z = trajectories(term, d, rates, z0, record.dt)
            for k in np.flatnonzero(np.all(np.isfinite(Z), axis=0)):
                score = _score(settled, Z[cut:, k], library, latent, pairs, fitting)
                if score is not None:
                    found.append(Candidate(drive, term, float(rates[k]), float(taus[k]), score))
    return sorted(found, key=lambda c: -c.score)


def leaders(found, most: int = LEADERS) -> list:
    """The best candidate of each (drive, law) within :data:`SCREEN_NATS` of the best, best first, ``most`` of them:
    each starts an output-error fit."""
    seen: set = set()
    out: list = []
    for c in found:
        if c.score < found[0].score - SCREEN_NATS:
            break
        if (c.drive.name, c.law.name) not in seen and len(out) < most:
            seen.add((c.drive.name, c.law.name))
            out.append(c)
    return out


def with_latent(record: Trajectory, latent: str, z: np.ndarray, states) -> Trajectory:
    """``record`` with the column ``latent`` (a guess of the latent state), its states in the model's order."""
    columns = {n: record.column(n) for n in record.state_names} | {latent: z}
    X = np.column_stack([columns[n] for n in states])
    return Trajectory(record.t, X, record.inputs, tuple(states), record.input_names)


def regress(records, library: Library, states, pairs, fitting) -> IdentifiedModel:
    """The equation-error model of ``records`` (every one of ``states`` a column), as :func:`symsbl.identify` fits
    it with ``fitting``'s options."""
    problem = regression_stats(
        records, library, derivative="weak", chunk_size=fitting.chunk_size, jit=fitting.jit, states=states
    )
    return fit_stats(problem, rvm=fitting.rvm, kinematics=pairs, selection=fitting.rule)


def _fit(record: Trajectory, library: Library, states, pairs, fitting) -> IdentifiedModel | None:
    """:func:`regress` quietly; None where the library cannot be evaluated on ``record`` (a square root of a
    negative level)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return regress(record, library, states, pairs, fitting)
    except (DataError, np.linalg.LinAlgError, FloatingPointError):
        return None


def _score(record, z, library, latent, pairs, fitting) -> float | None:
    """The summed log evidence of the equations of ``record``'s states (the measured ones) with ``z`` as one more
    column (an input of the regression: its own equation is not regressed), each by one relevance vector machine
    (the screen needs no support search: it took 95 % of the time and changed no ranking measured); None where
    the library cannot be evaluated."""
    measured = record.state_names
    inputs = np.column_stack([record.inputs, z])
    seen = Trajectory(record.t, record.states, inputs, measured, (*record.input_names, latent))
    positions = {x for x, _ in pairs}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            problem = regression_stats(
                seen, library, derivative="weak", chunk_size=fitting.chunk_size, jit=fitting.jit, states=measured
            )
            fits = [
                fit_rvm(fitting.template, problem.stats, k)
                for k, n in enumerate(problem.target_names)
                if n not in positions
            ]
    except (DataError, np.linalg.LinAlgError, FloatingPointError):
        return None
    scores = [float(f.log_evidence_) for f in fits]
    return float(sum(scores)) if scores and all(math.isfinite(v) for v in scores) else None


def guesses(best: Candidate, records, latent: str, states) -> list:
    """Each record with the candidate ``best``'s simulated latent state as a column (the refinement's starting
    guess)."""
    out = []
    for r in records:
        d = _values(best.drive, r)
        z0, _ = equilibria(best.law, np.array([best.rate]), float(np.mean(d)))
        z = trajectories(best.law, d, np.array([best.rate]), z0, r.dt)[:, 0]
        if not np.all(np.isfinite(z)):
            raise SimulationError(
                expected(
                    f"latent law {best.law.name} driven by {best.drive.name}",
                    "a simulation that stays finite on every record",
                    "non-finite values (no equilibrium at a record's mean drive, or the law left its domain)",
                    "leave that record out, or add laws of the latent state to the library",
                    raw=True,
                )
            )
        out.append(with_latent(r, latent, z, states))
    return out


def start_model(best: Candidate, record: Trajectory, library: Library, states, latent, pairs, fitting):
    """The hidden branch's start: ``z' = d - a phi(z)`` (``d``'s coefficient fixed) and the measured equations
    regressed with ``z`` from ``record`` (which holds the guess as a column)."""
    fitted = _fit(record.slice(int(SETTLE * record.n_samples)), library, states, pairs, fitting)
    if fitted is None:
        raise SimulationError(
            expected(
                "measured equations",
                f"a regression on the latent law {best.law.name}",
                "a library that cannot be evaluated on the records",
                "check the library's terms on the measured range (a square root of a negative level)",
                raw=True,
            )
        )
    a = best.rate
    law = (
        TermEstimate(expr=best.drive.expr, coef=1.0, std=0.0, fixed=True),
        TermEstimate(expr=best.law.expr, coef=-a, std=0.01 * a),
    )
    equation = Equation(latent, law, np.diag([0.0, (0.01 * a) ** 2]), math.nan, math.nan, 0)
    equations = tuple(equation if eq.lhs == latent else eq for eq in fitted.equations)
    measured = tuple(n for n in states if n != latent and n in record.state_names)
    return dataclasses.replace(fitted, equations=equations, measured=measured)
