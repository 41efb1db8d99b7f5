"""Identification: trajectories x library -> :class:`~symsbl.model.IdentifiedModel`.

The pipeline, for each trajectory:

1. the derivative strategy turns the sampled states into regression targets ``Y`` and tells which
   samples feed which rows;
2. the compiled evaluator builds the dictionary chunk by chunk, the strategy reduces each chunk
   to rows (identity for pointwise differences, window integrals for the weak form), and the
   chunks are accumulated into one :class:`~symsbl.rvm.GramStats` shared by every state equation;
3. one :class:`~symsbl.rvm.RVM` per state equation is fitted from the shared statistics;
4. an evidence-guided search refines each support and near-equivalent candidates are resolved
   by parsimony (:mod:`symsbl.selection`).

The model is expressed in the data's physical units: a term ``sin(x1)`` is the sine of the
measured ``x1``. Columns are normalised only inside the RVM.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from .data import Trajectory
from .derivatives import get_differentiator
from .errors import DataError, LibraryError
from .evaluator import Evaluator
from .library import Library
from .model import Equation, IdentifiedModel, TermEstimate
from .progress import Progress
from .rvm import RVM, GramStats
from .selection import complexity, fit_rvm, search_support

__all__ = ["identify", "fit_stats", "regression_stats", "RegressionStats"]

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


def _check_names(traj: Trajectory, library: Library) -> None:
    available = list(traj.state_names) + list(traj.input_names)
    missing = [n for n in library.variable_names if n not in available]
    if missing:
        raise LibraryError(
            f"library uses variables {missing} that are not in the data; the data has states "
            f"{list(traj.state_names)} and inputs {list(traj.input_names)}. Declare the library "
            "with symbols named like the data's columns."
        )


def _columns(traj: Trajectory, library: Library) -> np.ndarray:
    _check_names(traj, library)
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


def _row_chunks(traj, library, evaluator, diff, chunk_size, bar) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    Y = diff.targets(traj.t, traj.states)
    Z = _columns(traj, library)
    n_rows = len(Y)
    # about chunk_size samples per block, whatever the number of samples behind one row
    s0, s1 = diff.sample_span(0, 1)
    block = max(1, chunk_size // max(1, s1 - s0 - 1))
    for r0 in range(0, n_rows, block):
        r1 = min(r0 + block, n_rows)
        s0, s1 = diff.sample_span(r0, r1)
        D = diff.reduce(evaluator.evaluate(Z[s0:s1]))[: r1 - r0]
        yield D, Y[r0:r1]
        bar.update(r1 - r0)


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
        Samples per chunk: memory is ``O(chunk_size * n_terms + n_terms^2)`` whatever the length.
    jit : {"auto", True, False}
        Compile the dictionary with a C compiler when available.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> problem = symsbl.regression_stats(train, library)
    >>> problem.derivative, problem.stats.n_samples, problem.stats.n_terms
    (WeakForm(window=44, power=4), 186, 11)
    """
    trajectories = _as_trajectories(data)
    if not isinstance(library, Library):
        raise LibraryError(f"library must be a symsbl Library; received {type(library).__name__}.")
    longest = max(trajectories, key=lambda tr: tr.n_samples)
    diff = get_differentiator(derivative).resolve(longest.t, longest.states, n_terms=len(library))
    for traj in trajectories:  # validate everything before the expensive pass
        _check_variation(traj)
        _check_names(traj, library)
    n_rows = sum(diff.n_rows(traj.n_samples) for traj in trajectories)
    if n_rows <= len(library):
        raise DataError(
            f"the data give {n_rows} regression rows for {len(library)} candidate terms; "
            "identification needs more rows than terms. Use longer records, a smaller library "
            f"(lower degree) or a derivative with more rows than {type(diff).__name__}."
        )
    evaluator = Evaluator(library, chunk_size=chunk_size, jit=jit)
    total = None
    with Progress(f"dictionary ({len(library)} terms) and Gram", total=n_rows, unit="rows") as bar:
        for traj in trajectories:
            part = GramStats.from_chunks(_row_chunks(traj, library, evaluator, diff, chunk_size, bar))
            total = part if total is None else total + part
    traj = trajectories[0]
    return RegressionStats(total, library, traj.state_names, traj.input_names, diff)


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

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> model = symsbl.identify(train, library)
    >>> print(model)
    x1' = 1.0002(5e-4) x2
    x2' = -9990(23) x1 - 20.07(0.06) x2 - 9.999e8(8e5) x1^3 + 0.9992(7e-4) F
    >>> model.equation("x2").names
    ['x1', 'x2', 'x1**3', 'F']
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

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> problem = symsbl.regression_stats(train, library)
    >>> symsbl.fit_stats(problem).equation("x2").names
    ['x1', 'x2', 'x1**3', 'F']
    """
    template = RVM() if rvm is None else rvm
    library = problem.library
    stats = problem.stats
    keys = [complexity(t.sympy) for t in library.terms]
    variables = {v.name(): v for v in library.variables}
    states = tuple(variables[n] if n in variables else _symbol(n) for n in problem.state_names)
    inputs = tuple(variables[n] if n in variables else _symbol(n) for n in problem.input_names)
    equations = []
    with Progress("fit", total=len(problem.state_names), unit="equations") as bar:
        for k, lhs in enumerate(problem.state_names):
            equations.append(_fit_equation(library, stats, k, lhs, template, keys, equivalence_nats))
            bar.update()
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


def _fit_equation(library, stats, k, lhs, template, keys, equivalence_nats) -> Equation:
    """The sparse equation of state ``k``: RVM, support search, parsimony."""
    first = fit_rvm(template, stats, k)
    if len(first.active_) == 0:
        return Equation(lhs, (), np.zeros((0, 0)), float(first.noise_var_), float(first.log_evidence_), int(stats.n_samples))
    active, alternatives, search = search_support(first, stats, k, keys, template, equivalence_nats)
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
    return Equation(lhs, tuple(terms), np.array(final.sigma_), float(final.noise_var_), float(final.log_evidence_),
                    int(stats.n_samples))


def _symbol(name: str):
    import casadi as ca

    return ca.SX.sym(name)
