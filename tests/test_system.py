"""OdeSystem construction and evaluation; the paper's five systems against hand-written numpy forms."""

import casadi as ca
import numpy as np
import pytest
from helpers import exactly

from symsbl import OdeSystem, SimulationError, systems

RNG = np.random.default_rng(0)
X2 = RNG.standard_normal((5000, 2)) * [1e-2, 1.0]  # includes a final partial chunk
U = RNG.standard_normal((5000, 1)) * 100


def oscillator(g, m=1.0, c=20.0, k=1e4):
    x1, x2, F = X2[:, 0], X2[:, 1], U[:, 0]
    return np.column_stack([x2, (F - c * x2 - k * x1 - g(x1, x2)) / m])


@pytest.mark.parametrize(
    "system, g",
    [
        (systems.linear(), lambda x1, x2: 0.0),
        (systems.quadratic_damping(), lambda x1, x2: 2.0 * x2**2),
        (systems.duffing(), lambda x1, x2: 1e9 * x1**3),
        (systems.coulomb(), lambda x1, x2: np.sign(x2)),
        (systems.duffing(k3=5.0, m=2.0, c=3.0, k=7.0), lambda x1, x2: 5.0 * x1**3),
    ],
)
def test_oscillators_match_numpy(system, g):
    m, c, k = (dict(zip(system.parameter_names, system.parameter_values))[n] for n in "mck")
    np.testing.assert_allclose(system.evaluate_rhs(X2, U), oscillator(g, m, c, k), rtol=1e-13, atol=1e-9)
    assert system.state_names == ("x1", "x2") and system.input_names == ("F",)


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_bouc_wen_matches_classical_form(n):
    s = systems.bouc_wen(n=n)
    X = np.column_stack([X2, RNG.standard_normal(5000) * 50])
    x1, x2, x3 = X.T
    A, a, b = 6800.0, 1.5, -1.5
    x3dot = -a * np.abs(x2) * np.abs(x3) ** (n - 1) * x3 - b * x2 * np.abs(x3) ** n + A * x2
    expected = np.column_stack([x2, U[:, 0] - 20 * x2 - 1e4 * x1 - x3, x3dot])
    np.testing.assert_allclose(s.evaluate_rhs(X, U), expected, rtol=1e-12, atol=1e-6)
    assert s.state_names == ("x1", "x2", "x3") and not s.is_smooth


def test_bouc_wen_rejects_bad_exponent():
    with pytest.raises(
        SimulationError, match=exactly("n: expected a positive integer exponent (e.g. 2 or 3), received 2.5")
    ):
        systems.bouc_wen(n=2.5)


def test_smoothness():
    assert systems.linear().is_smooth and systems.duffing().is_smooth and systems.quadratic_damping().is_smooth
    assert not systems.coulomb().is_smooth and not systems.bouc_wen().is_smooth
    assert systems.bouc_wen().is_continuous and systems.duffing().is_continuous  # abs is a kink, not a jump
    assert not systems.coulomb().is_continuous


def test_parameters_are_symbols_and_reparameterise():
    s = systems.duffing()
    assert s.parameter_names == ("m", "c", "k", "k3")
    assert s.parameter_values == (1.0, 20.0, 1e4, 1e9)
    s2 = s.with_parameters(k3=2e9, c=0.0)
    np.testing.assert_allclose(s2.evaluate_rhs(X2, U), oscillator(lambda x1, x2: 2e9 * x1**3, c=0.0), rtol=1e-13)
    assert s.parameter_values[3] == 1e9  # the original is unchanged
    with pytest.raises(
        SimulationError,
        match=exactly("parameters: expected names among ['m', 'c', 'k', 'k3'] of 'duffing', received ['k9']"),
    ):
        s.with_parameters(k9=1.0)


def test_rhs_function_interface():
    f = systems.coulomb(kc=3.0).rhs_function()
    assert f.name() == "rhs" and f.name_in() == ["x", "u"] and f.name_out() == ["xdot"]
    np.testing.assert_allclose(np.array(f([0.01, -0.5], [7.0])).ravel(), [-0.5, 7 + 10 - 100 + 3.0])


def test_custom_system_without_inputs():
    s = systems.lorenz()
    X = RNG.standard_normal((10, 3))
    x, y, z = X.T
    expected = np.column_stack([10 * (y - x), x * (28 - z) - y, x * y - 8 / 3 * z])
    np.testing.assert_allclose(s.evaluate_rhs(X), expected, rtol=1e-13)
    assert s.n_inputs == 0


def test_identified_style_system_from_arbitrary_sx():
    x, u = ca.SX.sym("x"), ca.SX.sym("u")
    s = OdeSystem((x,), (u,), (-2.5 * x + 0.3 * ca.sin(x) * ca.fabs(u) + 4,), name="identified")
    X, Uu = np.array([[0.5], [-1.0]]), np.array([[2.0], [-3.0]])
    np.testing.assert_allclose(
        s.evaluate_rhs(X, Uu)[:, 0], -2.5 * X[:, 0] + 0.3 * np.sin(X[:, 0]) * np.abs(Uu[:, 0]) + 4
    )
    assert not s.is_smooth
    const = OdeSystem((x,), (), (1.5,))
    np.testing.assert_allclose(const.evaluate_rhs(np.zeros((3, 1))), 1.5)


def test_construction_errors():
    x, y, u, p = (ca.SX.sym(n) for n in ("x", "y", "u", "p"))
    with pytest.raises(
        SimulationError,
        match=exactly(
            "states[0]: expected a scalar casadi.SX symbol, received "
            "SX((2.*x)); create symbols with symsbl.symbols('x1 x2')"
        ),
    ):
        OdeSystem((2 * x,), (), (x,))
    with pytest.raises(
        SimulationError,
        match=exactly(
            "states[0]: expected a scalar casadi.SX symbol, received "
            "SX([v_0, v_1]); create symbols with symsbl.symbols('x1 x2')"
        ),
    ):
        OdeSystem((ca.SX.sym("v", 2),), (), (x,))
    with pytest.raises(
        SimulationError, match=exactly("rhs: expected one expression per state ['x', 'y'], received 1 expressions")
    ):
        OdeSystem((x, y), (), (x,))
    with pytest.raises(
        SimulationError,
        match=exactly(
            "rhs: expected expressions of the declared symbols ['u', 'x'], "
            "received expressions "
            "that also use ['p']; declare them"
        ),
    ):
        OdeSystem((x,), (u,), (p * x,))
    with pytest.raises(
        SimulationError, match=exactly("parameter_values: expected one value per parameter (1), received 0 values")
    ):
        OdeSystem((x,), (), (p * x,), (p,))
    with pytest.raises(
        SimulationError,
        match=exactly(
            "states, inputs and parameters together: expected distinct "
            "symbol names, "
            "received ['x', 'x']; rename the repeated ['x']"
        ),
    ):
        OdeSystem((x,), (ca.SX.sym("x"),), (x,))
    with pytest.raises(
        SimulationError, match=exactly("rhs: expected scalar expressions, received one of shape (2, 1)")
    ):
        OdeSystem((x,), (), (ca.vertcat(x, x),))
    with pytest.raises(
        SimulationError, match=exactly("rhs: expected CasADi SX, numbers or sympy expressions, received str")
    ):
        OdeSystem((x,), (), ("x",))


def test_evaluate_rhs_shape_errors():
    s = systems.linear()
    with pytest.raises(SimulationError, match=exactly("X: expected shape (n_samples, 2), received shape (4, 3)")):
        s.evaluate_rhs(np.zeros((4, 3)), np.zeros((4, 1)))
    with pytest.raises(SimulationError, match=exactly("U: expected shape (4, 1), received shape (3, 1)")):
        s.evaluate_rhs(np.zeros((4, 2)), np.zeros((3, 1)))


def test_to_sympy():
    sp = pytest.importorskip("sympy")
    pytest.importorskip("symsbl._symbolic.symbols")
    eqs = systems.duffing().to_sympy()
    x1, x2, F, t = (sp.Symbol(n, real=True) for n in ("x1", "x2", "F", "t"))
    assert eqs[0].lhs == sp.Derivative(x1, t) and sp.simplify(eqs[0].rhs - x2) == 0
    assert sp.simplify(eqs[1].rhs - (F - 20 * x2 - 10000 * x1 - 1e9 * x1**3)) == 0
    k3 = sp.Symbol("k3", real=True)
    assert k3 in systems.duffing().to_sympy(substitute=False)[1].rhs.free_symbols


def test_sympy_rhs_accepted():
    sp = pytest.importorskip("sympy")
    pytest.importorskip("symsbl._symbolic.symbols")
    x, u = ca.SX.sym("x"), ca.SX.sym("u")
    xs, us = sp.symbols("x u", real=True)
    s = OdeSystem((x,), (u,), (-3 * xs + us * sp.sign(xs),))
    np.testing.assert_allclose(s.evaluate_rhs([[2.0], [-1.0]], [[5.0], [5.0]])[:, 0], [-6 + 5, 3 - 5])
