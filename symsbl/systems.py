"""Ready-made systems: the five single-degree-of-freedom oscillators of Fuentes et al. (2019), and Lorenz.

All oscillators are ``m y'' + c y' + k y + g(x) = F`` in state-space form (Sec. 3, Eqs. 18-19)::

    x1' = x2
    x2' = (F - c x2 - k x1 - g) / m

with states ``x1`` (displacement, m), ``x2`` (velocity, m/s), input ``F`` (force, N) and the paper's
linear parameters ``m = 1, c = 20, k = 1e4`` (natural frequency 15.9 Hz). The nonlinearities ``g`` and
their values are those of Table 1. Every parameter is an SX symbol with a value, so
``duffing().with_parameters(k3=5e8)`` re-parameterises without rebuilding.

References
----------
R. Fuentes, N. Dervilis, K. Worden, E. J. Cross, "Efficient parameter identification and model
selection in nonlinear dynamical systems via sparse Bayesian learning", J. Phys.: Conf. Ser. 1264 (2019).
"""

from __future__ import annotations

import casadi as ca

from ._base.errors import SimulationError, expected
from ._simulation.ode import OdeSystem

__all__ = ["linear", "quadratic_damping", "duffing", "coulomb", "bouc_wen", "lorenz"]


def _oscillator(name, m, c, k, *, g=lambda x1, x2, p: 0, extra=(), third_state=None, third_rhs=None):
    """Build the SDOF oscillator with nonlinearity ``g(x1, x2, params)`` and extra named parameters."""
    x1, x2, F = ca.SX.sym("x1"), ca.SX.sym("x2"), ca.SX.sym("F")
    names = ("m", "c", "k") + tuple(n for n, _ in extra)
    values = (m, c, k) + tuple(v for _, v in extra)
    p = {n: ca.SX.sym(n) for n in names}
    states = (x1, x2) if third_state is None else (x1, x2, third_state)
    g_expr = g(x1, x2, p)
    rhs = [x2, (F - p["c"] * x2 - p["k"] * x1 - g_expr) / p["m"]]
    if third_state is not None:
        rhs.append(third_rhs(x2, third_state, p))
    return OdeSystem(states, (F,), tuple(rhs), tuple(p.values()), tuple(float(v) for v in values), name)


def linear(m: float = 1.0, c: float = 20.0, k: float = 1e4) -> OdeSystem:
    """System 1: the linear oscillator, ``g = 0``."""
    return _oscillator("linear", m, c, k)


def quadratic_damping(k2: float = 2.0, m: float = 1.0, c: float = 20.0, k: float = 1e4) -> OdeSystem:
    """System 2: quadratic damping, ``g = k2 * x2**2`` exactly as in Table 1 (not ``k2 x2 |x2|``)."""
    return _oscillator("quadratic_damping", m, c, k, g=lambda x1, x2, p: p["k2"] * x2**2, extra=(("k2", k2),))


def duffing(k3: float = 1e9, m: float = 1.0, c: float = 20.0, k: float = 1e4) -> OdeSystem:
    """System 3: Duffing oscillator, ``g = k3 * x1**3``."""
    return _oscillator("duffing", m, c, k, g=lambda x1, x2, p: p["k3"] * x1**3, extra=(("k3", k3),))


def coulomb(kc: float = 1.0, m: float = 1.0, c: float = 20.0, k: float = 1e4) -> OdeSystem:
    """System 4: Coulomb friction, ``g = kc * sign(x2)``.

    Table 1 prints ``sign(x1)``; the text (and the physics) say the friction opposes the velocity, so
    ``sign(x2)`` is used. The right-hand side is discontinuous at ``x2 = 0``: simulate it with a fixed-step
    method (``simulate(..., method="auto")`` does), never with an adaptive one.
    """
    return _oscillator("coulomb", m, c, k, g=lambda x1, x2, p: p["kc"] * ca.sign(x2), extra=(("kc", kc),))


def bouc_wen(
    A: float = 6800.0, n: int = 3, a: float = 1.5, b: float = -1.5, m: float = 1.0, c: float = 20.0, k: float = 1e4
) -> OdeSystem:
    """System 5: Bouc-Wen hysteresis with restoring force ``g = x3`` and Eq. (20)::

        x3' = -a |x2| x3**n       - b x2 |x3**n| + A x2     (n odd)
        x3' = -a |x2| x3**(n-1) |x3| - b x2 |x3**n| + A x2  (n even)

    Both branches equal the classical ``-a |x2| |x3|**(n-1) x3 - b x2 |x3|**n + A x2``. ``n`` is a structural
    exponent (a positive integer), not a parameter symbol. The paper's Fig. 2e uses ``n = 2``.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise SimulationError(expected("n", "a positive integer exponent (e.g. 2 or 3)", n))
    x3 = ca.SX.sym("x3")

    def x3dot(x2, x3, p):
        if n % 2:
            hyst = x3**n
        else:
            hyst = x3 ** (n - 1) * ca.fabs(x3)
        return -p["a"] * ca.fabs(x2) * hyst - p["b"] * x2 * ca.fabs(x3**n) + p["A"] * x2

    return _oscillator(
        "bouc_wen",
        m,
        c,
        k,
        g=lambda x1, x2, p: x3,
        extra=(("A", A), ("a", a), ("b", b)),
        third_state=x3,
        third_rhs=x3dot,
    )


def lorenz(sigma: float = 10.0, rho: float = 28.0, beta: float = 8.0 / 3.0) -> OdeSystem:
    """The Lorenz system (no inputs): ``x' = sigma (y - x)``, ``y' = x (rho - z) - y``, ``z' = x y - beta z``."""
    x, y, z = ca.SX.sym("x"), ca.SX.sym("y"), ca.SX.sym("z")
    s, r, bt = ca.SX.sym("sigma"), ca.SX.sym("rho"), ca.SX.sym("beta")
    return OdeSystem(
        (x, y, z), (), (s * (y - x), x * (r - z) - y, x * y - bt * z), (s, r, bt), (sigma, rho, beta), "lorenz"
    )
