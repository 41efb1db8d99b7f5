"""Identification: trajectories x library -> :class:`~symsbl.model.IdentifiedModel`.

The pipeline, for each trajectory:

1. the derivative strategy turns the sampled states into regression targets ``Y`` and tells which
   samples feed which rows;
2. the compiled evaluator builds the dictionary chunk by chunk, the strategy reduces each chunk
   to rows (identity for pointwise differences, window integrals for the weak form), and the
   chunks are accumulated into one :class:`~symsbl.rvm.GramStats` shared by every state equation;
3. one :class:`~symsbl.rvm.RVM` per state equation is fitted from the shared statistics;
4. near-equivalent candidates are resolved by parsimony (see :func:`identify`).

The model is expressed in the data's physical units: a term ``sin(x1)`` is the sine of the
measured ``x1``. Columns are normalised only inside the RVM.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator, Sequence

import numpy as np
import sympy as sp

from .data import Trajectory
from .derivatives import get_differentiator
from .errors import DataError, LibraryError
from .evaluator import Evaluator
from .library import Library
from .model import Equation, IdentifiedModel, TermEstimate
from .rvm import RVM, GramStats

__all__ = ["identify", "fit_stats", "regression_stats", "RegressionStats", "complexity"]

#: Candidates whose columns, normalised, have a cosine above this with a kept term are tested
#: for equivalence by an exact refit (a cheap pre-filter; the decision is by evidence).
EQUIVALENCE_COSINE = 0.99


@dataclass(frozen=True)
class RegressionStats:
    """Sufficient statistics of one identification problem.

    Attributes
    ----------
    stats : GramStats
        ``D^T D``, ``D^T Y`` ... over all regression rows of all trajectories.
    library : Library
        The candidate library (columns of D).
    state_names, input_names : tuple of str
        Targets (one per state) and inputs.
    derivative : object
        The derivative strategy used.
    """

    stats: GramStats
    library: Library
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    derivative: object


def _as_trajectories(data) -> list[Trajectory]:
    if isinstance(data, Trajectory):
        return [data]
    if isinstance(data, (list, tuple)) and data and all(isinstance(d, Trajectory) for d in data):
        names = {(d.state_names, d.input_names) for d in data}
        if len(names) > 1:
            raise DataError(
                "all trajectories must have the same state and input names; received "
                + "; ".join(f"states={s}, inputs={i}" for s, i in sorted(names))
                + "."
            )
        return list(data)
    raise DataError(
        "data must be a Trajectory or a non-empty list of Trajectories; received "
        f"{type(data).__name__}. Read files with symsbl.read_trajectory."
    )


def _columns(traj: Trajectory, library: Library) -> np.ndarray:
    available = list(traj.state_names) + list(traj.input_names)
    missing = [n for n in library.variable_names if n not in available]
    if missing:
        raise LibraryError(
            f"library uses variables {missing} that are not in the data; the data has states "
            f"{list(traj.state_names)} and inputs {list(traj.input_names)}. Declare the library "
            "with symbols named like the data's columns."
        )
    return np.column_stack([traj.column(n) for n in library.variable_names])


def _check_variation(traj: Trajectory) -> None:
    for j, name in enumerate(traj.state_names):
        col = traj.states[:, j]
        if np.ptp(col) <= 1e-12 * max(np.max(np.abs(col)), 1e-300):
            raise DataError(
                f"state {name!r} has no variation (constant {col[0]:.6g}); its derivative is zero "
                "and its equation cannot be identified. Remove it from the states or record "
                "a response in which it moves."
            )


def _row_chunks(traj, library, evaluator, diff, block) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    Y = diff.targets(traj.t, traj.states)
    Z = _columns(traj, library)
    n_rows = len(Y)
    for r0 in range(0, n_rows, block):
        r1 = min(r0 + block, n_rows)
        s0, s1 = diff.sample_span(r0, r1)
        D = diff.reduce(evaluator.evaluate(Z[s0:s1]))[: r1 - r0]
        yield D, Y[r0:r1]


def regression_stats(data, library: Library, *, derivative="weak", chunk_size: int = 4096, jit="auto") -> RegressionStats:
    """Accumulate the regression statistics of ``data`` over ``library`` chunk by chunk.

    Parameters
    ----------
    data : Trajectory or list of Trajectory
        Sampled states (and inputs); several trajectories add their rows.
    library : Library
        Candidate terms; its variables must be named like the data's states and inputs.
    derivative : str or derivative strategy
        ``"weak"`` (default), ``"central"``, ``"point"``, ``"savgol"`` or a strategy instance.
    chunk_size : int
        Rows per chunk: memory is ``O(chunk_size * n_terms + n_terms^2)`` whatever the length.
    jit : {"auto", True, False}
        Compile the dictionary with a C compiler when available.
    """
    trajectories = _as_trajectories(data)
    if not isinstance(library, Library):
        raise LibraryError(f"library must be a symsbl Library; received {type(library).__name__}.")
    longest = max(trajectories, key=lambda tr: tr.n_samples)
    diff = get_differentiator(derivative).resolve(longest.t, longest.states, n_terms=len(library))
    evaluator = Evaluator(library, chunk_size=chunk_size, jit=jit)
    total = None
    n_rows = 0
    for traj in trajectories:
        _check_variation(traj)
        _columns(traj, library)  # fail early on missing columns
        n_rows += diff.n_rows(traj.n_samples)
        part = GramStats.from_chunks(_row_chunks(traj, library, evaluator, diff, chunk_size))
        total = part if total is None else total + part
    if n_rows <= len(library):
        raise DataError(
            f"the data give {n_rows} regression rows for {len(library)} candidate terms; "
            "identification needs more rows than terms. Use longer records, a smaller library "
            f"(lower degree) or a derivative with more rows than {type(diff).__name__}."
        )
    traj = trajectories[0]
    return RegressionStats(total, library, traj.state_names, traj.input_names, diff)


def complexity(expr: sp.Expr) -> tuple[int, int, int]:
    """Parsimony key of a candidate term: smaller is simpler.

    Terms are ranked first by function class (polynomial < with ``Abs`` < with ``sign`` <
    ``sin``/``cos`` < anything else, e.g. ``tan``), then by polynomial degree, then by
    the number of operations.
    """
    funcs = {type(f).__name__ for f in expr.atoms(sp.Function)}
    if not funcs:
        rank = 0
    elif funcs <= {"Abs"}:
        rank = 1
    elif funcs <= {"Abs", "sign"}:
        rank = 2
    elif funcs <= {"Abs", "sign", "sin", "cos"}:
        rank = 3
    else:
        rank = 4
    try:
        degree = int(sp.Poly(expr.replace(sp.Abs, lambda a: a), *expr.free_symbols).total_degree()) if expr.free_symbols else 0
    except (sp.PolynomialError, sp.GeneratorsNeeded):
        degree = 99
    return rank, degree, int(sp.count_ops(expr))


def _subset(stats: GramStats, cols: Sequence[int], target: int) -> GramStats:
    cols = list(cols)
    return GramStats(
        stats.gram[np.ix_(cols, cols)],
        stats.dty[cols][:, [target]],
        stats.yty[[target]],
        stats.y_sum[[target]],
        stats.n_samples,
    )


def _fit(template: RVM, stats: GramStats, target: int, prune_nats=None) -> RVM:
    params = template.get_params()
    params["free"] = ()
    if prune_nats is not None:
        params["prune_nats"] = prune_nats
    return RVM(**params).fit_stats(stats, target=target)


class _SupportSearch:
    """Evidence-guided local search over supports around the RVM's answer.

    The fast RVM is a greedy optimiser: a term admitted early (``sin(x2)`` before ``x2``) can
    leave it in a local optimum that needs two moves to escape (``sin(x2) + 1107 x2**3``
    mimicking ``x2``). The search scores a support by the RVM's own objective, the log
    evidence minus the per-term penalty, refitting the RVM on the support's columns only, and
    tries single additions and single swaps. Candidates are pre-filtered by their correlation
    with the residual (for additions) or with the residual plus the swapped term's
    contribution (for swaps), ``n_candidates`` each, plus every column nearly collinear with
    the swapped term.
    """

    def __init__(self, stats, target, template, prune_nats, n_candidates=8):
        self.stats, self.target, self.template = stats, target, template
        self.prune_nats, self.k = prune_nats, n_candidates
        G = stats.gram
        self.norms = np.sqrt(np.maximum(np.diag(G), 1e-300))
        self.cache: dict[tuple, tuple[float, list[int], RVM]] = {}

    def score(self, cols) -> tuple[float, list[int], RVM]:
        """Penalised log evidence of the RVM refitted on ``cols``, the columns it keeps
        (sorted), and the fit itself."""
        key = tuple(sorted(cols))
        if key not in self.cache:
            fit = _fit(self.template, _subset(self.stats, key, self.target), 0, self.prune_nats)
            kept = [key[i] for i in fit.active_]
            value = fit.log_evidence_ - self.prune_nats * len(kept)
            self.cache[key] = (value, kept, fit)
        return self.cache[key]

    def coefficients(self, kept, fit) -> np.ndarray:
        """Full-length coefficient vector of a fit returned by :meth:`score`."""
        mu = np.zeros(self.stats.n_terms)
        mu[kept] = fit.coef_[fit.active_]
        return mu

    def _top(self, scores, exclude):
        order = np.argsort(-np.abs(scores) / self.norms, kind="stable")
        return [int(i) for i in order if i not in exclude][: self.k]

    def collinear(self, j, exclude):
        G = self.stats.gram
        cos = np.abs(G[j]) / (self.norms * self.norms[j])
        return [int(i) for i in np.flatnonzero(cos > EQUIVALENCE_COSINE) if i != j and i not in exclude]

    def run(self, active, max_moves=20):
        best, active, fit = self.score(active)
        G, b = self.stats.gram, self.stats.dty[:, self.target]
        for _ in range(max_moves):
            mu = self.coefficients(active, fit)
            corr = b - G @ mu
            trials = [active + [i] for i in self._top(corr, active)]
            for pos, j in enumerate(active):
                others = active[:pos] + active[pos + 1 :]
                pool = self._top(corr + mu[j] * G[:, j], active) + self.collinear(j, active)
                trials += [others + [i] for i in dict.fromkeys(pool)]
            improved = None
            for cols in trials:
                value, kept, f = self.score(cols)
                if value > best + 1e-6 and (improved is None or value > improved[0]):
                    improved = (value, kept, f)
            if improved is None:
                break
            best, active, fit = improved
        return best, active, fit


def _search_support(first: RVM, stats, target, keys, template, tol):
    """Local search from the RVM's support, then parsimony among near-equivalents.

    Returns the support and, per kept column, the near-equivalent columns whose swap costs
    less than ``tol`` nats (the simplest of each group is the one kept)."""
    search = _SupportSearch(stats, target, template, first.prune_nats_)
    best, active, _ = search.run([int(i) for i in first.active_])
    alternatives: dict[int, list[int]] = {}
    for _ in range(len(active) + 1):
        changed = False
        for pos, j in enumerate(active):
            others = active[:pos] + active[pos + 1 :]
            equal = []
            for i in search.collinear(j, active):
                value, kept, _ = search.score(others + [i])
                if value >= best - tol and i in kept and set(kept) - {i} == set(others):
                    equal.append((i, value))
            if not equal:
                continue
            group = [j] + [i for i, _ in equal]
            simplest = min(group, key=lambda i: (keys[i], i))
            alternatives[simplest] = sorted(set(group) - {simplest}, key=lambda i: (keys[i], i))
            if simplest != j:
                alternatives.pop(j, None)
                active = sorted(others + [simplest])
                best = dict(equal)[simplest]
                changed = True
                break
        if not changed:
            break
    return sorted(active), alternatives, search


def identify(
    data,
    library: Library,
    *,
    derivative="weak",
    rvm: RVM | None = None,
    chunk_size: int = 4096,
    jit="auto",
    equivalence_nats: float = 2.0,
) -> IdentifiedModel:
    """Identify one sparse ODE per state from sampled trajectories.

    Parameters
    ----------
    data : Trajectory or list of Trajectory
        Measured or simulated states and inputs. Every state gets an equation, including
        kinematic ones (``x1' = x2`` is found, not assumed).
    library : Library
        Candidate terms, e.g. :func:`symsbl.library.paper`.
    derivative : str or derivative strategy
        How the targets are built: ``"weak"`` (default; integral form on non-overlapping
        windows), ``"central"``, ``"point"`` (the paper's), ``"savgol"``.
    rvm : RVM, optional
        Template estimator (options are copied; it is not modified). Default ``RVM()``.
    chunk_size : int
        Rows per chunk in the dictionary evaluation.
    jit : {"auto", True, False}
        Compile the dictionary with a C compiler when available.
    equivalence_nats : float
        Near-equivalent candidates: a kept term is swapped for a simpler candidate (see
        :func:`complexity`) when the swap costs less than this many nats of log evidence, and
        every candidate within this margin is reported as indistinguishable. At 16 mm of
        displacement ``x1``, ``sin(x1)`` and ``tan(x1)`` differ by parts in 10^4 and the
        evidence cannot separate them; parsimony then keeps ``x1``.

    Returns
    -------
    IdentifiedModel
    """
    problem = regression_stats(data, library, derivative=derivative, chunk_size=chunk_size, jit=jit)
    return fit_stats(problem, rvm=rvm, equivalence_nats=equivalence_nats)


def fit_stats(problem: RegressionStats, *, rvm: RVM | None = None, equivalence_nats: float = 2.0) -> IdentifiedModel:
    """Fit one sparse equation per state from accumulated regression statistics.

    This is the second half of :func:`identify`, for statistics built elsewhere (streamed
    chunks, several machines): the same model comes out of the same statistics.

    Parameters
    ----------
    problem : RegressionStats
        From :func:`regression_stats` or accumulated by other means.
    rvm, equivalence_nats
        As in :func:`identify`.
    """
    template = RVM() if rvm is None else rvm
    library = problem.library
    stats = problem.stats
    keys = [complexity(t.sympy) for t in library.terms]
    variables = {v.name(): v for v in library.variables}
    states = tuple(variables[n] if n in variables else _symbol(n) for n in problem.state_names)
    inputs = tuple(variables[n] if n in variables else _symbol(n) for n in problem.input_names)
    equations = []
    for k, lhs in enumerate(problem.state_names):
        first = _fit(template, stats, k)
        if len(first.active_) == 0:
            equations.append(Equation(lhs, (), np.zeros((0, 0)), float(first.noise_var_), float(first.log_evidence_), int(stats.n_samples)))
            continue
        active, alternatives, search = _search_support(first, stats, k, keys, template, equivalence_nats)
        _, kept, final = search.score(active)
        terms = []
        for pos, col in enumerate(kept):
            idx = int(final.active_[pos])
            terms.append(
                TermEstimate(
                    expr=library.terms[col].expr,
                    coef=float(final.coef_[idx]),
                    std=float(math.sqrt(final.sigma_[pos, pos])),
                    alpha=float(final.alpha_[idx]),
                    evidence=float(final.evidence_contribution_[pos]),
                    alternatives=tuple(library.terms[i].name for i in alternatives.get(col, ())),
                )
            )
        equations.append(
            Equation(lhs, tuple(terms), np.array(final.sigma_), float(final.noise_var_), float(final.log_evidence_), int(stats.n_samples))
        )
    return IdentifiedModel(
        states=states,
        inputs=inputs,
        equations=tuple(equations),
        metadata={
            "derivative": type(problem.derivative).__name__,
            "n_candidates": len(library),
            "n_rows": int(stats.n_samples),
        },
    )


def _symbol(name: str):
    import casadi as ca

    return ca.SX.sym(name)
