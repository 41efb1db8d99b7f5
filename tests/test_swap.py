"""Swaps: a term the equation error chose for a sum of others is exchanged for the library term that does its
work (``symsbl/_refine/swap.py``)."""

from __future__ import annotations

import numpy as np
import pytest
from reference_oscillator import multisine
from scipy.integrate import solve_ivp
from scipy.optimize import minimize

import symsbl
from symsbl._refine.swap import swap_gains

#: A softening oscillator with linear and quadratic drag: ``m x'' + c x' + q x'|x'| + k x + k3 x^3 = F``.
M, C, Q, K, K3 = 0.7, 0.35, 0.08, 640.0, -1.5e5
FS, SECONDS = 1500.0, 8.0


def _quadratic_optimum(S, g, theta, alpha, free, fixed):
    """The log posterior's quadratic model ``g'd - d'Sd/2 - sum alpha (theta + d)^2 / 2`` maximised over the
    coefficients ``free`` by BFGS, with those of ``fixed`` (a dict) held at the given moves and the rest at 0:
    the maximum and the coefficients ``theta + d`` there."""

    def full(x):
        d = np.zeros(theta.size)
        d[free] = x
        for k, v in fixed.items():
            d[k] = v
        return d

    def negative(x):
        d = full(x)
        return -(g @ d - 0.5 * d @ S @ d - 0.5 * np.sum(alpha * (theta + d) ** 2))

    found = minimize(negative, np.zeros(len(free)), method="BFGS", options={"gtol": 1e-10})
    return -found.fun, theta + full(found.x)


def test_the_swap_gain_is_the_quadratic_models_constrained_optimum():
    """Against a brute-force maximisation of the quadratic model: every swap of a random problem (six held
    coefficients, three candidates at zero), one term or two for one, gains what BFGS finds with the terms
    removed and the newcomer free, less what it finds at the held structure."""
    rng = np.random.default_rng(3)
    n, held = 9, np.arange(6)
    A = rng.standard_normal((40, n))
    S = A.T @ A
    theta = np.zeros(n)
    theta[held] = rng.standard_normal(held.size)
    alpha = rng.uniform(0.1, 2.0, n)
    g = rng.standard_normal(n) * 3.0
    moves = [((k,), j) for k in (0, 2, 5) for j in (6, 7, 8)] + [((1, 4), 7), ((0, 3), 8)]
    gains, moved = swap_gains(S, g, theta, alpha, held, moves)
    here, _ = _quadratic_optimum(S, g, theta, alpha, list(held), {})
    for (out, j), gain, coef in zip(moves, gains, moved):
        free = [a for a in held if a not in out] + [j]
        there, at = _quadratic_optimum(S, g, theta, alpha, free, {k: -theta[k] for k in out})
        assert gain == pytest.approx(there - here, rel=1e-6, abs=1e-6)
        np.testing.assert_allclose(coef, at, atol=1e-6)


def _record(seed: int) -> symsbl.Trajectory:
    """A record of the drag oscillator under a 1-30 Hz multisine, integrated by DOP853 on the analytic force,
    with 0.6 % white noise on x and v."""
    rng = np.random.default_rng(seed)
    force = multisine(2.0, 1.0, 30.0, SECONDS, rng)
    t = np.arange(int(FS * SECONDS)) / FS

    def rhs(tt, s):
        return [s[1], (force.scalar(tt) - C * s[1] - Q * s[1] * abs(s[1]) - K * s[0] - K3 * s[0] ** 3) / M]

    opts = dict(method="DOP853", rtol=1e-10, atol=1e-13, max_step=1 / FS)
    X = solve_ivp(rhs, (0.0, t[-1]), [0.0, 0.0], t_eval=t, **opts).y.T
    Y = X + 0.006 * X.std(axis=0) * rng.standard_normal(X.shape)
    return symsbl.Trajectory(t, Y, force(t)[:, None], ("x", "v"), ("F",))


@pytest.mark.parametrize("seed", [0, 2, 4])
def test_a_drag_law_the_equation_error_took_for_tan_or_sin_comes_out_exact(seed):
    """The equation error takes ``tan(v)`` (seed 0) or leaves the drag out (seeds 2, 4), and the output error
    made it up with ``tan(v)`` or ``sin(v)`` beside ``v`` (before the swaps: 2 of seeds 0-7 exact). With the
    swaps: the structure ``F, x, v, v|v|, x^3`` exactly, every coefficient within four posterior standard
    deviations of the truth, and a white noise model."""
    x, v, F = symsbl.symbols("x v F")
    model = symsbl.identify(_record(seed), symsbl.paper([x, v], [F], degree=3), kinematics="x:v")
    assert model.metadata["refine"]["swaps"], "the exact structure came without a swap: the premise is gone"
    eq = next(e for e in model.equations if e.lhs == "v")
    truth = {"F": 1 / M, "x": -K / M, "v": -C / M, "v*Abs(v)": -Q / M, "x**3": -K3 / M}
    assert sorted(eq.names) == sorted(truth)
    for term in eq.terms:
        assert abs(term.coef - truth[term.name]) < 4 * term.std, (term.name, term.coef, term.std)
    # the noise model is chosen again on the exact structure's residual, not kept from the first fit's
    noise = model.metadata["refine"]["noise"]
    assert [noise[c]["model"] for c in ("x", "v")] == ["white", "white"]


def test_a_white_first_fit_makes_no_swap_and_a_fixed_noise_order_stays():
    """A hardening oscillator (``tests/reference_oscillator.py``, exact in the library, 1 % white noise): the
    first fit's residual is white, so nothing is swapped and the structure is the truth's. With the drag
    record and a noise order the caller fixed (AR(2)), the swaps still run and the order stays 2."""
    from reference_oscillator import HARDENING, library, record

    model = symsbl.identify(record(HARDENING, 3), library(), kinematics="x:v")
    assert model.metadata["refine"]["swaps"] == []
    assert sorted(model.equation("v").names) == sorted(HARDENING.truth())
    options = symsbl.RefineOptions(noise=2)
    x, v, F = symsbl.symbols("x v F")
    lib = symsbl.paper([x, v], [F], degree=3)
    fixed = symsbl.identify(_record(0), lib, kinematics="x:v", refine_options=options)
    assert fixed.metadata["refine"]["swaps"]
    assert {len(c["ar"]) for c in fixed.metadata["refine"]["noise"].values()} == {2}
