"""Forward screening: which library terms would raise the output-error fit if they were added.

Run by :func:`symsbl.refine` when a state of the model is not measured.

The equation-error fit proposes a structure, its runners-up and the terms it found
indistinguishable. When a state is estimated rather than measured (a velocity differentiated from a
displacement), a small term can be missing from all three: its equation-error evidence is lost in
the estimate's error although the simulated response needs it. The screen asks the output error
directly. One sensitivity pass of the fitted structure, extended by candidate terms held at zero,
gives for each candidate the gain of the quadratic model of the data term when that candidate is
added and the current terms and initial states re-adjust (a score, or Lagrange-multiplier,
statistic):

    gain_j = 1/2 (g_j - S_jA P^-1 g_A)^2 / (S_jj - S_jA P^-1 S_Aj),   P = S_AA + diag(alpha_A),

where ``S`` is the data's information with every segment's initial state eliminated (a Schur
complement) and ``g`` the gradient with the same elimination. The pass runs on evenly spaced
windows of at most :data:`SCREEN_SAMPLES` samples, starting on the fitted trajectory. Candidates
whose gain there clears the selection penalty at that size are handed to the term selection, which
decides on refits and the evidence of all the samples refined on. An effect whose gain on the whole
record barely clears the penalty can stay below it on the screened samples and is not proposed.
"""

from __future__ import annotations

import numpy as np

from .._base.rule import complexity
from .laplace import x0_pinv
from .problem import window_plan

__all__ = ["screen_terms", "score_gains", "blocks_info", "SCREEN_SAMPLES", "MAX_SCREENED", "PER_EQUATION"]

#: Samples the screening pass runs on at most (evenly spaced windows of the refined records).
SCREEN_SAMPLES = 2**13
#: Candidate terms screened at most, over all equations (the simplest first).
MAX_SCREENED = 32
#: Candidates handed to the term selection per equation at most (the largest gains).
PER_EQUATION = 3


def _pool(model, library) -> dict:
    """Per fitted equation, the library terms it does not hold, simplest first, at most :data:`MAX_SCREENED`."""
    fitted = [eq for eq in model.equations if not eq.fixed]
    if not fitted:
        return {}
    share = max(1, MAX_SCREENED // len(fitted))
    order = sorted(range(len(library)), key=lambda k: complexity(library.terms[k].sympy))
    pool = {}
    for eq in fitted:
        present = set(eq.names) | {a for t in eq.terms for a in t.alternatives}
        names = [library.terms[k].name for k in order if library.terms[k].name not in present]
        if names:
            pool[eq.lhs] = names[:share]
    return pool


def _reduced(H: np.ndarray, g: np.ndarray, npar: int):
    """Information and gradient of the coefficients with every segment's initial state eliminated."""
    Htt, Htx = H[:, :npar, :npar].sum(axis=0), H[:, :npar, npar:]
    pinv, _, _ = x0_pinv(H[:, npar:, npar:])
    S = Htt - np.einsum("kpi,kij,kqj->pq", Htx, pinv, Htx)
    gr = g[:, :npar].sum(axis=0) - np.einsum("kpi,kij,kj->p", Htx, pinv, g[:, npar:])
    return 0.5 * (S + S.T), gr


def gains(S: np.ndarray, g: np.ndarray, base: np.ndarray, alpha_base: np.ndarray, others: np.ndarray) -> np.ndarray:
    """The quadratic model's gain (nats) of adding each of ``others`` to ``base`` (see the module text)."""
    P = S[np.ix_(base, base)] + np.diag(alpha_base)
    B = S[np.ix_(others, base)]
    solved = np.linalg.solve(P, np.column_stack([B.T, g[base]]))
    info = S[others, others] - np.einsum("ja,aj->j", B, solved[:, :-1])
    score = g[others] - B @ solved[:, -1]
    scale = np.maximum(np.abs(S[others, others]), 1e-300)
    ok = info > 1e-10 * scale  # a candidate the base already spans gains nothing (and is not divided by ~0)
    gain = np.zeros(info.shape)
    gain[ok] = 0.5 * score[ok] ** 2 / info[ok]
    return gain


def score_gains(blocks, npar: int, base: np.ndarray, alpha_base: np.ndarray, others: np.ndarray) -> np.ndarray | None:
    """The gain (nats) of adding each coefficient of ``others`` to those of ``base`` (prior precisions
    ``alpha_base``), from the blocks of one pass of ``npar`` coefficients (see the module text); None when the
    blocks are not finite."""
    information = _information(blocks, npar)
    return None if information is None else gains(*information, base, alpha_base, others)


def blocks_info(passes, sol) -> tuple[np.ndarray, np.ndarray] | None:
    """The data's information and gradient of every coefficient of ``passes`` at the fit ``sol``, its segments'
    initial states eliminated (None when the pass is not finite)."""
    with np.errstate(all="ignore"):
        blocks = passes.sensitivities(sol.theta, sol.X0, passes.segments(sol.starts), sol.w, sol.ar)
    return _information(blocks, sol.theta.size)


def _information(blocks, npar: int) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`_reduced` of ``blocks``, None when they are not finite."""
    if not (np.all(np.isfinite(blocks.H)) and np.all(np.isfinite(blocks.g))):
        return None
    return _reduced(blocks.H, blocks.g, npar)


def screen_terms(engine_of, model, records, solution, base_engine, library, threshold) -> dict:
    """Library terms worth trying in each equation, ``{state: [name, ...]}`` (largest gain first).

    Parameters
    ----------
    engine_of : callable
        ``engine_of(records, candidates)`` builds an :class:`~symsbl._refine.engine.Engine` of ``model``
        extended by ``candidates`` (``{state: [(expr, 0.0), ...]}``) on ``records``.
    model : IdentifiedModel
        The structure fitted.
    records : list of Trajectory
        The records refined on.
    solution : Solution
        The fit of ``model`` on ``records`` by ``base_engine``.
    base_engine : Engine
    library : Rebased
        The candidate library in the model's symbols (:class:`~symsbl._refine.candidates.Rebased`).
    threshold : callable
        ``threshold(n_obs)``: nats a candidate's gain on ``n_obs`` screened measurements must exceed (the
        selection's penalty per term at that size).
    """
    pool = _pool(model, library)
    if not pool:
        return {}
    plan, _ = window_plan([r.n_samples for r in records], SCREEN_SAMPLES)
    windows = [records[k] if (a, b) == (0, records[k].n_samples) else records[k].slice(a, b) for k, a, b in plan]
    candidates = {lhs: [(library[n].expr, 0.0) for n in names] for lhs, names in pool.items()}
    engine = engine_of(windows, candidates)
    passes = engine.passes
    theta = np.zeros(len(engine.positions))
    theta[engine.base] = solution.theta[base_engine.base]
    length = min(int(solution.length), int(passes.records.lengths.max()))
    starts = passes.segment_starts(length)
    # the segments start on the fitted trajectory (the candidates are at zero: the same states)
    main = base_engine.passes
    origin = np.concatenate([main.records.starts[k] + np.arange(a, b) for k, a, b in plan])
    with np.errstate(all="ignore"):
        X0 = main.simulate(solution.theta, solution.X0, main.segments(solution.starts))[origin[starts]]
        w = np.atleast_2d(solution.w)[[k for k, _, _ in plan]]  # each window at its record's noise
        blocks = passes.sensitivities(theta, X0, passes.segments(starts), w, solution.ar)
    others = np.setdiff1d(np.arange(theta.size), engine.base)
    found = score_gains(blocks, theta.size, engine.base, solution.alpha[base_engine.base], others)
    if found is None or not np.all(np.isfinite(X0)):
        return {}
    limit = threshold(int(passes.n_obs.sum()))
    out: dict[str, list[str]] = {}
    for k, gain in sorted(zip(others, found), key=lambda kv: -kv[1]):
        i, j = engine.positions[k]
        eq = engine.full.equations[i]
        if gain > limit and len(out.get(eq.lhs, [])) < PER_EQUATION:
            out.setdefault(eq.lhs, []).append(eq.terms[j].name)
    return out
