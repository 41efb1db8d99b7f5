"""symsbl.RVM as pysindy's optimizer: a pysindy pipeline keeps its derivatives and library and
gets the RVM's selection through pysindy's own wrapper for scikit-learn regressors.

pysindy is not a dependency of symsbl (only of the ``dev`` and ``bench`` extras); these tests run where
it is installed.
"""

import numpy as np
import pytest

import symsbl

ps = pytest.importorskip(
    "pysindy", reason="pysindy is not installed (pip install '.[dev]'); the RVM-in-pysindy tests need it"
)

pytestmark = [
    # pysindy 2.1's own warnings about its axis labels, not about symsbl
    pytest.mark.filterwarnings("ignore::pysindy.utils._axes.AxesWarning"),
    pytest.mark.filterwarnings("ignore::DeprecationWarning:pysindy"),
]

NAMES = ["x1", "x2", "F"]


def rvm_optimizer(**params):
    """The RVM inside pysindy: ``unbias=False`` keeps the RVM's posterior mean (pysindy's unbias
    step refits least squares on the support without column scaling, which is ill-conditioned
    for terms such as x1**3 ~ 1e-6)."""
    return ps.WrappedOptimizer(symsbl.RVM(**params), unbias=False)


def fitted(train, library, optimizer, differentiation=None):
    model = ps.SINDy(optimizer=optimizer, feature_library=library, differentiation_method=differentiation)
    model.fit(train.states, t=train.t, u=train.inputs, feature_names=NAMES)
    return model


def equations(model):
    names = model.get_feature_names()
    return [{n: c for n, c in zip(names, row, strict=True) if c != 0} for row in model.coefficients()]


def test_sindy_with_the_rvm_finds_duffing_without_a_threshold(duffing_train):
    model = fitted(duffing_train, ps.PolynomialLibrary(degree=3), rvm_optimizer(), ps.FiniteDifference())
    x1, x2 = equations(model)
    assert set(x1) == {"x2"} and set(x2) == {"x1", "x2", "F", "x1^3"}
    truth = {"x1": -1e4, "x2": -20.0, "F": 1.0, "x1^3": -1e9}
    for term, value in truth.items():
        assert x2[term] == pytest.approx(value, rel=0.01)
    assert x1["x2"] == pytest.approx(1.0, rel=1e-3)


def test_the_wrapped_rvm_is_symsbls_rvm_on_pysindys_regression(duffing_train):
    """Each equation's coefficients are those of ``symsbl.RVM().fit`` on pysindy's features and
    finite-difference targets: the wrapper adds nothing and loses nothing."""
    model = fitted(
        duffing_train, ps.PolynomialLibrary(degree=3), rvm_optimizer(prune_nats="bic"), ps.FiniteDifference()
    )
    theta = np.asarray(model.optimizer.Theta_)
    x_dot = np.asarray(ps.FiniteDifference()(duffing_train.states, t=duffing_train.t))
    for k in range(2):
        direct = symsbl.RVM(prune_nats="bic").fit(theta, x_dot[:, k])
        np.testing.assert_allclose(model.coefficients()[k], direct.coef_, rtol=1e-12, atol=0)
    fitted_rvms = model.optimizer.optimizer.estimators_  # one clone per equation, with its posterior
    assert [type(r) for r in fitted_rvms] == [symsbl.RVM, symsbl.RVM]
    assert all(r.prune_nats_ == pytest.approx(0.5 * np.log(len(theta))) for r in fitted_rvms)


def test_the_rvm_takes_pysindys_weak_form(duffing_train):
    np.random.seed(0)  # pysindy draws its subdomains from numpy's global generator
    library = ps.WeakPDELibrary(
        function_library=ps.PolynomialLibrary(degree=3), spatiotemporal_grid=duffing_train.t, K=400, H_xt=[0.003], p=4
    )
    x1, x2 = equations(fitted(duffing_train, library, rvm_optimizer()))
    assert set(x1) == {"x2"}
    assert {"x1", "x2", "F", "x1^3"} <= set(x2)
    assert x2["x1^3"] == pytest.approx(-1e9, rel=0.01)
