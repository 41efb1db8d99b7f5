"""Locating a disagreement: where in the phase plane and in time a model misses the data."""

from __future__ import annotations

import math

import numpy as np

from .._data.residuals import effective_fraction
from .._symbolic.evaluator import Evaluator
from .._symbolic.library import Library
from .._validate.validate import validate_model
from .results import Disagreement

__all__ = ["locate"]


def locate(model, train, heldout, design, displacement, velocity, measure, measured=None) -> Disagreement:
    """Where ``model`` disagrees with the records: residual regions, the jump across v = 0 and the phase-plane
    map of the equation residual of ``model``'s structure refitted on ``train``, and the held-out error over
    time (of the ``measured`` states, default all; an unmeasured velocity's column holds an estimate, which the
    equation residual uses)."""
    diff = design.derivative
    y, r = _equation_residual(model, train, design, velocity)
    xv = diff.reduce(
        np.column_stack(
            [train.column(displacement) if displacement else np.zeros(train.n_samples), train.column(velocity)]
        )
    )
    x, v = xv[:, 0], xv[:, 1]
    X, V = max(np.max(np.abs(x)), 1e-300), max(np.max(np.abs(v)), 1e-300)
    energy = r**2 / max(np.sum(r**2), 1e-300)
    masks = [
        ("velocity reversals (|v| < 0.15 V)", np.abs(v) < 0.15 * V),
        ("peak speed (|v| > 0.75 V)", np.abs(v) > 0.75 * V),
    ]
    if displacement:
        masks.append(("large displacement (|x| > 0.75 X)", np.abs(x) > 0.75 * X))
    regions = tuple((name, float(m.mean()), float(energy[m].sum())) for name, m in masks)
    up, down = r[(v > 0) & (v < 0.15 * V)], r[(v < 0) & (v > -0.15 * V)]
    jump, jump_z = 0.0, 0.0
    if len(up) > 1 and len(down) > 1:
        jump = float(up.mean() - down.mean())
        jump_z = jump / math.sqrt(up.var() / len(up) + down.var() / len(down) + 1e-300)
    edges_x, edges_v = np.linspace(-X, X, 9), np.linspace(-V, V, 9)
    total, _, _ = np.histogram2d(x, v, [edges_x, edges_v], weights=r)
    count, _, _ = np.histogram2d(x, v, [edges_x, edges_v])
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_map = np.where(count > 0, total / count, np.nan)
    mids, err = _error_profile(model, heldout, measure, measured)
    residual_nrmse = float(math.sqrt(np.mean(r**2)) / max(np.std(y), 1e-300))
    words = _in_words(residual_nrmse, regions, jump, jump_z, mids, err)
    return Disagreement(
        residual_nrmse,
        effective_fraction(r),
        regions,
        jump,
        float(jump_z),
        (edges_x, edges_v, mean_map),
        (np.array(mids), np.array(err)),
        words,
    )


def _equation_residual(model, train, design, velocity):
    """The velocity equation's target rows on ``train`` and their residual after its structure's own fit."""
    diff = design.derivative
    eq = model.equation(velocity)
    lib = Library([t.expr for t in eq.terms], design.variables)
    Z = np.column_stack([train.column(n) for n in lib.variable_names])
    D = diff.reduce(Evaluator(lib, jit=False).evaluate(Z))
    y = diff.targets(train.t, train.column(velocity)[:, None])[:, 0]
    # the structure's own least-squares fit on this record: what its terms cannot explain here, whichever
    # records and weights the model's coefficients were fitted on
    coef = np.linalg.lstsq(D, y, rcond=None)[0] if D.shape[1] else np.zeros(0)
    return y, y - D @ coef


def _error_profile(model, heldout, measure, measured):
    """The held-out simulation error over ten segments of time, with the segments' mid times (empty otherwise)."""
    if measure != "simulation":
        return [], []
    sim = validate_model(model, heldout, method="rk4").simulated
    channels = [n for n in sim.state_names if (measured is None or n in measured) and n in heldout.state_names]
    meas = np.column_stack([heldout.column(n) for n in channels])[: sim.n_samples]
    segments = np.array_split(np.arange(sim.n_samples), 10)
    scale = np.std(meas, axis=0)
    simulated = np.column_stack([sim.column(n) for n in channels])
    err = [float(np.mean(np.sqrt(np.mean((meas[s] - simulated[s]) ** 2, axis=0)) / scale)) for s in segments]
    mids = [float(heldout.t[s].mean()) for s in segments]
    return mids, err


def _in_words(residual_nrmse, regions, jump, jump_z, mids, err) -> str:
    """The disagreement in words: the residual's size, where it concentrates, its jump and the worst time."""
    worst = max(regions, key=lambda reg: reg[2] / max(reg[1], 1e-12))
    words = [f"equation residual {100 * residual_nrmse:.3g} % of the target's spread"]
    if worst[2] > 1.5 * worst[1]:
        words.append(
            f"concentrated at {worst[0]}: {100 * worst[2]:.0f} % of its energy in {100 * worst[1]:.0f} % of the rows"
        )
    else:
        words.append("spread evenly over the phase plane")
    if abs(jump_z) > 5:
        words.append(f"it jumps by {jump:.3g} (z = {jump_z:.0f}) across v = 0")
    if err:
        i = int(np.argmax(err))
        words.append(f"held-out simulation error largest near t = {mids[i]:.3g} s ({100 * err[i]:.3g} %)")
    return "; ".join(words)
