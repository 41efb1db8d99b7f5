"""Output-error evidence of candidate effects: a screen of all of them, refits of the leading ones.

The current model is fitted by output error (:mod:`symsbl._refine`) on every record at once, each
with its own initial state. Every candidate is then scored in two steps:

1. a **screen**: one sensitivity pass of the model extended by every candidate (held at zero) gives,
   for each, the gain of the quadratic model of the data term when its coefficients join and the
   others re-adjust (the score statistic of :mod:`symsbl._refine.screen`, for a block of terms);
2. **refits** of the candidates that lead the screen (the best variant of each effect and place):
   the exact change of the Laplace log evidence when the candidate joins, every coefficient and
   initial state refitted, on the same compiled structure and segmentation.

A residual correlated in time (coloured noise, a closed loop) counts fewer independent samples than
it has: each gain is multiplied by the effective fraction ``N_eff / N`` of the residual of the fit
that includes the candidate (:func:`symsbl._refine.engine.residual_fraction`).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from .._base.errors import SimulationError
from .._data.trajectory import Trajectory
from .._model import IdentifiedModel
from .._refine.candidates import prior
from .._refine.engine import Engine, Settings, record_horizon, residual_fraction
from .._refine.problem import window_plan
from .._refine.result import to_model
from .._refine.screen import _reduced
from .._simulation.signals import Sampled
from .._simulation.simulate import simulate

__all__ = ["Scorer", "block_gain", "SCREEN_SAMPLES", "REFITS"]

#: Samples the screening pass runs on at most (evenly spaced windows of the records).
SCREEN_SAMPLES = 2**13
#: Candidates refitted per iteration at most (the screen's leaders, one variant per effect and place).
REFITS = 4


def block_gain(S: np.ndarray, g: np.ndarray, base: np.ndarray, alpha_base: np.ndarray, idx) -> float:
    """Quadratic-model gain (nats) of adding the coefficients ``idx`` together to ``base``:
    ``1/2 s^T I^-1 s`` with the score ``s`` and information ``I`` of ``idx`` given ``base``."""
    idx = np.asarray(idx, dtype=int)
    P = S[np.ix_(base, base)] + np.diag(alpha_base)
    B = S[np.ix_(idx, base)]
    solved = np.linalg.solve(P, np.column_stack([B.T, g[base]]))
    info = S[np.ix_(idx, idx)] - B @ solved[:, :-1]
    score = g[idx] - B @ solved[:, -1]
    scale = np.maximum(np.abs(np.diag(S[np.ix_(idx, idx)])), 1e-300)
    if np.any(np.diag(info) <= 1e-10 * scale):
        return 0.0
    return float(0.5 * score @ np.linalg.lstsq(info, score, rcond=None)[0])


def with_candidates(model: IdentifiedModel, candidates) -> dict:
    """``{state: [(expr, 0.0), ...]}`` of every candidate's terms, in order."""
    out: dict = {}
    for c in candidates:
        for state, exprs in c.additions:
            out.setdefault(state, []).extend((e, 0.0) for e in exprs)
    return out


def positions_of(engine: Engine, model: IdentifiedModel, candidates) -> list[list[int]]:
    """Each candidate's coefficient indices in ``engine`` (built by :func:`with_candidates`)."""
    where = {p: k for k, p in enumerate(engine.positions)}
    row = {eq.lhs: i for i, eq in enumerate(model.equations)}
    next_term = {eq.lhs: len(eq.terms) for eq in model.equations}
    out = []
    for c in candidates:
        idx = []
        for state, exprs in c.additions:
            for _ in exprs:
                idx.append(where[(row[state], next_term[state])])
                next_term[state] += 1
        out.append(idx)
    return out


class Scorer:
    """The current model fitted by output error on every record, and the scores of candidates against it."""

    def __init__(self, model: IdentifiedModel, records, measured, settings: Settings):
        self.model, self.records, self.measured, self.settings = model, list(records), tuple(measured), settings
        self.engine = Engine(model, self.records, self.measured, settings, {})
        alpha = prior(self.engine)
        theta0 = np.array(self.engine.param.theta0, dtype=float)
        self.solution = self.engine.fit(self.engine.base, theta0, alpha)
        self.fraction = residual_fraction(self.engine, self.solution)

    @functools.cached_property
    def simulated(self) -> np.ndarray:
        """The fit's simulated states on every sample ``(n_total, nx)``, each segment from its fitted start."""
        passes, sol = self.engine.passes, self.solution
        with np.errstate(all="ignore"):
            return passes.simulate(sol.theta, sol.X0, passes.segments(sol.starts))

    @property
    def residual(self) -> np.ndarray:
        """Measured minus simulated, ``(n_total, n_measured)``, in the layout of ``engine.passes.records``."""
        passes, sol = self.engine.passes, self.solution
        with np.errstate(all="ignore"):
            return passes.records.Y - passes.outputs(sol.theta, sol.X0, passes.segments(sol.starts))

    @property
    def log_evidence(self) -> float:
        return float(self.solution.posterior.log_evidence)

    def fitted(self) -> IdentifiedModel:
        return to_model(self.engine, self.solution, {"refine": {"log_evidence": self.log_evidence}})

    @functools.cached_property
    def horizon(self) -> int | None:
        """Samples within which the fitted model amplifies a state error 10^4-fold, when that is shorter than the
        longest record (a hypersensitive record under this model); else None."""
        return record_horizon(self.engine, self.solution)

    def screen(self, candidates) -> np.ndarray:
        """The quadratic-model gain of each candidate (nats, before its penalty), from one sensitivity pass on
        evenly spaced windows of at most :data:`SCREEN_SAMPLES` samples, scaled to all the samples."""
        sol, main = self.solution, self.engine
        plan, _ = window_plan([r.n_samples for r in self.records], SCREEN_SAMPLES)
        windows = [
            self.records[k] if (a, b) == (0, self.records[k].n_samples) else self.records[k].slice(a, b)
            for k, a, b in plan
        ]
        engine = Engine(
            self.model,
            windows,
            self.measured,
            dataclasses.replace(self.settings, jit=False),
            with_candidates(self.model, candidates),
        )
        passes = engine.passes
        theta = np.zeros(len(engine.positions))
        theta[engine.base] = sol.theta[main.base]
        starts = passes.segment_starts(min(int(sol.length), int(passes.records.lengths.max())))
        origin = np.concatenate([main.passes.records.starts[k] + np.arange(a, b) for k, a, b in plan])
        with np.errstate(all="ignore"):
            w = np.atleast_2d(sol.w)[[k for k, _, _ in plan]]  # each window at its record's noise
            blocks = passes.sensitivities(theta, self.simulated[origin[starts]], passes.segments(starts), w, sol.ar)
        H, g = blocks.H, blocks.g
        if not (np.all(np.isfinite(H)) and np.all(np.isfinite(g))):
            return np.zeros(len(candidates))
        S, gr = _reduced(H, g, theta.size)
        scale = float(main.passes.n_obs.sum()) / max(float(passes.n_obs.sum()), 1.0)
        alpha_base = sol.alpha[main.base]
        out = []
        for idx in positions_of(engine, self.model, candidates):
            try:
                out.append(scale * block_gain(S, gr, engine.base, alpha_base, idx))
            except np.linalg.LinAlgError:
                out.append(0.0)
        return np.array(out)

    def refit(self, candidates) -> list[dict | None]:
        """Each candidate added alone and everything refitted: ``{"gain", "fraction", "model", "coefs", "stds"}``
        (``None`` when the model with it runs away on a record)."""
        engine = Engine(self.model, self.records, self.measured, self.settings, with_candidates(self.model, candidates))
        alpha = prior(engine)
        alpha[engine.base] = self.solution.alpha[self.engine.base]
        theta = np.zeros(len(engine.positions))
        theta[engine.base] = self.solution.theta[self.engine.base]
        base = engine.fit(engine.base, theta, alpha, warm=self.solution)
        out: list[dict | None] = []
        for idx in positions_of(engine, self.model, candidates):
            active = np.concatenate([engine.base, idx]).astype(int)
            try:
                sol = engine.fit(
                    active, base.theta, np.where(np.isin(np.arange(alpha.size), idx), alpha, base.alpha), warm=base
                )
            except SimulationError:
                out.append(None)
                continue
            post = sol.posterior
            where = [list(sol.active).index(k) for k in idx]
            out.append(
                {
                    "gain": float(post.log_evidence - base.posterior.log_evidence),
                    "fraction": residual_fraction(engine, sol),
                    "model": to_model(engine, sol, {"refine": {"log_evidence": float(post.log_evidence)}}),
                    "coefs": post.mean[where],
                    "stds": post.std[where],
                    "w": sol.channel_w,
                    "horizon": record_horizon(engine, sol),
                }
            )
        return out

    def initial_states(self) -> list[np.ndarray]:
        """Each record's fitted initial state."""
        sol, starts = self.solution, self.engine.passes.records.starts
        return [sol.X0[int(np.searchsorted(sol.starts, s))] for s in starts]

    def null_gains(self, candidates, n_bootstrap: int, seed: int, penalties: np.ndarray) -> list[float]:
        """The largest screened gain (after penalties) on records simulated from the fitted model with white noise
        of the fitted level: the gains of "nothing missing" on data like these."""
        if n_bootstrap <= 0:
            return []
        model = self.fitted()
        system = model.to_system()
        std = {m: 1.0 / np.sqrt(w) for m, w in zip(self.measured, self.solution.channel_w)}
        rng = np.random.default_rng(seed)
        out: list[float] = []
        for _ in range(n_bootstrap):
            fakes = []
            for r, x0 in zip(self.records, self.initial_states()):
                U = Sampled(r.t, r.inputs) if r.inputs.shape[1] else None
                try:
                    clean = simulate(system, r.t, inputs=U, x0=x0, method="rk4", on_divergence="raise")
                except SimulationError:
                    return out
                cols = [
                    clean.column(n) + rng.standard_normal(r.n_samples) * std.get(n, 0.0)  # unmeasured: unused
                    for n in r.state_names
                ]
                fakes.append(Trajectory(r.t, np.column_stack(cols), r.inputs, r.state_names, r.input_names))
            try:
                fake = Scorer(self.model, fakes, self.measured, self.settings)
            except SimulationError:
                continue
            gains = fake.fraction * fake.screen(candidates) - penalties
            out.append(float(max(np.max(gains), 0.0)))
        return out
