"""The refined model: a fitted sub-structure and its output-error posterior as an :class:`IdentifiedModel`."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .._model import Equation, FitMethod, IdentifiedModel, TermEstimate
from .._model.outputs import latent_of
from .engine import Engine
from .laplace import reduce_model
from .solver import Solution

__all__ = ["to_model"]


def to_model(engine: Engine, sol: Solution, info: dict) -> IdentifiedModel:
    """The model of the fitted sub-structure with the output-error posterior; ``metadata["refine"]`` always
    holds the integrator settings (RK4 substeps, input interpolation) it was fitted with, which
    :func:`symsbl.validate_model` re-simulates it with (a Coulomb force of 5 % of the excitation,
    re-simulated with one step per sample instead of the fit's four, strayed 0.35 % from the truth)."""
    fitted = {
        "substeps": engine.substeps,
        "interpolation": engine.settings.interpolation,
        "noise": noise_record(engine.measured, sol),
    }
    fitted.update(_latent_start(engine, sol))
    info = dict(info, refine={**fitted, **info.get("refine", {})})
    post, active = sol.posterior, list(sol.active)
    where = {engine.positions[k]: n for n, k in enumerate(active)}
    std = post.std
    # an equation's noise is that of the channel that reads it: its state, or its right-hand side
    noise = {o.state or o.equation: 1.0 / w for o, w in zip(engine.outputs, sol.channel_w)}
    n_samples = int(sum(r.n_samples for r in engine.records))
    equations, free_order = [], []
    for i, eq in enumerate(engine.full.equations):
        if eq.fixed:
            equations.append(eq)
            continue
        kept = [j for j in range(len(eq.terms)) if (i, j) in where or eq.terms[j].fixed]
        idx = [where.get((i, j)) for j in kept]
        free_order += [n for n in idx if n is not None]
        terms = tuple(
            eq.terms[j]
            if n is None
            else TermEstimate(
                expr=eq.terms[j].expr,
                coef=float(post.mean[n]),
                std=float(std[n]),
                alpha=float(sol.alpha[active[n]]),
                evidence=float(sol.confirmed.get(active[n], -reduce_model(post, sol.alpha[active], [n])[0])),
                alternatives=eq.terms[j].alternatives,
            )
            for j, n in zip(kept, idx)
        )
        equations.append(
            Equation(
                eq.lhs,
                terms,
                _block(post.covariance, idx),
                noise.get(eq.lhs, math.nan),
                post.log_evidence,
                n_samples,
                runners_up=eq.runners_up,
                algebraic=eq.algebraic,
            )
        )
    plain = all(o.kind == "state" for o in engine.outputs) and not engine.model.outputs
    observed = (
        dict(measured=engine.measured)
        if plain
        else dict(measured=tuple(o.state for o in engine.outputs if o.state is not None), outputs=engine.outputs)
    )
    model = dataclasses.replace(
        engine.model,
        equations=tuple(equations),
        fit=FitMethod.OUTPUT_ERROR,
        metadata=dict(engine.model.metadata, **info),
        **observed,
    )
    return dataclasses.replace(model, joint_covariance=_joint(model, free_order, post.covariance))


def _latent_start(engine: Engine, sol: Solution) -> dict:
    """``{"latent_start": {state: median fitted initial value}}`` for the latent states (over the records' and
    segments' starts): where a record's latent state starts when nothing else says (a level under a square root
    cannot start at zero)."""
    names = engine.model.state_names
    latent = latent_of(names, engine.outputs, engine.model.kinematics)
    return {"latent_start": {n: float(np.median(sol.X0[:, names.index(n)])) for n in latent}} if latent else {}


def noise_record(measured, sol: Solution) -> dict:
    """Per measured channel, its noise model as the model file records it: ``{"model": "white" | "AR(p)",
    "ar": [a_1, ...], "innovation_std": sigma}`` (pooled over the records), and with several records
    ``"innovation_std_by_record": [sigma_1, ...]``."""
    out = {}
    w = np.atleast_2d(sol.w)
    pooled = sol.channel_w
    for c, name in enumerate(measured):
        ar = [] if sol.ar is None else [float(a) for a in sol.ar[c]]
        while ar and ar[-1] == 0.0:
            ar.pop()
        out[name] = {
            "model": f"AR({len(ar)})" if ar else "white",
            "ar": ar,
            "innovation_std": float(1.0 / math.sqrt(pooled[c])),
        }
        if w.shape[0] > 1:
            out[name]["innovation_std_by_record"] = [float(1.0 / math.sqrt(v)) for v in w[:, c]]
    return out


def _block(cov: np.ndarray, idx: list) -> np.ndarray:
    """The covariance of one equation's terms (``None``: a coefficient fixed by convention, zero rows)."""
    out = np.zeros((len(idx), len(idx)))
    free = [p for p, n in enumerate(idx) if n is not None]
    src = [idx[p] for p in free]
    out[np.ix_(free, free)] = cov[np.ix_(src, src)]
    return out


def _joint(model: IdentifiedModel, free_order: list, cov: np.ndarray) -> np.ndarray:
    """The free coefficients' covariance in :meth:`IdentifiedModel.parameters` order (zero for fixed ones)."""
    rows = []
    k = 0
    for eq in model.equations:
        for t in eq.terms:
            free = not eq.fixed and not t.fixed
            rows.append(free_order[k] if free else None)
            k += 1 if free else 0
    n = len(rows)
    out = np.zeros((n, n))
    fitted = [p for p, r in enumerate(rows) if r is not None]
    src = [r for r in rows if r is not None]
    out[np.ix_(fitted, fitted)] = cov[np.ix_(src, src)]
    return out
