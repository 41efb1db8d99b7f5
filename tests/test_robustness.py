"""Robustness beyond the paper: identification of systems, excitations and noise levels that
Fuentes et al. (2019) do not cover, each checked against the true equations.

- a pendulum, whose ``sin(x1)`` must win over its polynomial look-alikes at ~1 rad swings;
- cubic stiffness together with Coulomb friction;
- free decay from an initial condition, with no input and no input terms in the library;
- the three-state Lorenz system with a plain polynomial library;
- measurement noise of 1 % and 2 % on the paper's five systems, and where recovery fails.

Noise study (2 s at 32768 Hz, ``Sine(100, 10)``, Eq. 21 dictionary to degree 6, degree 4 for
Bouc-Wen, equation error (``refine=False``: the noise study and the cubic-plus-Coulomb study measure
the regression stage; the refinement is tested in ``test_refine.py``), noise seeds 0-4): exact support in 5/5 fits
on every system at 0.4 %, 1 % and 2 %; largest relative error of the terms carrying >= 5 % of their equation's variance
0.23 %, 0.59 % and 1.8 %; of all terms (Coulomb's ``sign(x2)``, 0.01 % of the variance, is the
worst) 3.3 %, 13 % and 24 %. Recovery starts to fail at 2.5 % (20/25 exact: Coulomb's sign(x2) is
dropped in 4 of 5 fits, quadratic damping's x2**2 becomes x2**2*|x2| once), is mostly lost at 3 %
(9/25) and entirely at 3.5 % and 5 % (0/25). The cause is the automatic weak-form window, which
shrinks as the noise grows (see :func:`test_weak_window_is_set_by_the_signal_not_the_noise`); with
the window chosen on the noise-free record the same data give 24/25 exact at 3 % and 16/25 at 5 %;
what still fails is Coulomb's sign(x2) dropped (4 of 5 at 5 %) and Duffing's x1 + x1**3 traded
for sign(x1) + x1*|x1| + x1**3*|x1| (1 at 3 %, 4 at 5 %), an answer whose penalised log evidence
is 10-20 nats below the truth's: the support-search local optimum of
:func:`test_cubic_stiffness_with_strong_coulomb_friction_under_a_sine`.
"""

from functools import cache

import casadi as ca
import numpy as np
import pytest

from symsbl import (
    Multisine,
    OdeSystem,
    RefineWarning,
    Sine,
    WeakForm,
    compare_to_truth,
    identify,
    paper,
    polynomial,
    simulate,
    symbols,
    systems,
    time_grid,
)
from symsbl._demo import CASES

FS = 32768.0


def _errors(comparison):
    """Relative coefficient errors, rounded, for assertion messages."""
    return {s: {n: round(e, 5) for n, e in terms.items()} for s, terms in comparison.relative_error.items()}


def _assert_within_posterior(model, truth: dict, n_std: float):
    """Every identified coefficient lies within ``n_std`` posterior standard deviations of the truth."""
    for eq in model.equations:
        for term in eq.terms:
            z = (term.coef - truth[eq.lhs][term.name]) / term.std
            assert abs(z) < n_std, (eq.lhs, term.name, term.coef, term.std)


# --- pendulum: sin(x1) against x1, x1**3, x1**5, tan(x1) -------------------------------------


def pendulum(g=9.81, length=1.0, c=0.5) -> OdeSystem:
    """``x1'' = -(g / L) sin(x1) - c x1' + F`` (F is a force per unit mass and length, rad/s^2)."""
    x1, x2, F = symbols("x1 x2 F")
    pg, pl, pc = symbols("g L c")
    return OdeSystem(
        states=(x1, x2),
        inputs=(F,),
        rhs=(x2, -(pg / pl) * ca.sin(x1) - pc * x2 + F),
        parameters=(pg, pl, pc),
        parameter_values=(g, length, c),
        name="pendulum",
    )


@cache
def _pendulum_record(rms: float, seed: int):
    # 20 s at 1 kHz (the natural frequency is 0.5 Hz); a multisine of period 20 s over 0.1-2 Hz.
    return simulate(
        pendulum(), time_grid(20.0, 1000.0), inputs=Multisine(rms=rms, f_min=0.1, f_max=2.0, seed=seed, period=20.0)
    )


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(5))
def test_pendulum_sine_wins_over_polynomial_look_alikes(seed):
    """Swings of 0.95-1.6 rad, where sin(x1) and x1 - x1**3/6 differ by about 1 %: the Eq. 21
    dictionary to degree 5 (x1, x1**3, x1**5, tan(x1), ... are all candidates) returns exactly
    x1' = x2, x2' = F - 9.81 sin(x1) - 0.5 x2; every coefficient within 1 % (largest seen 0.54 %)."""
    system = pendulum()
    clean = _pendulum_record(3.0, seed)
    assert np.max(np.abs(clean.states[:, 0])) > 0.9
    model = identify(clean.with_noise(0.004, seed=seed), paper(system.states, system.inputs, degree=5))
    truth = compare_to_truth(model, system, clean)
    assert truth.exact_support, (truth.missing, truth.spurious, str(model))
    assert truth.max_error() < 0.01, _errors(truth)


def test_pendulum_small_swings_fall_back_to_the_linear_term():
    """At 0.05 rad sin(x1) and x1 differ by 0.04 %: the equation-error fit cannot tell them apart, and
    parsimony keeps x1 (coefficient -g/L within 1 %) and reports sin(x1) as indistinguishable from it.
    The output-error fit resolves 0.04 % (its -g/L is 40x more precise) and finds sin(x1)."""
    system = pendulum()
    clean = _pendulum_record(0.1, 3)
    assert np.max(np.abs(clean.states[:, 0])) < 0.06
    library = paper(system.states, system.inputs, degree=5)
    refined = identify(clean.with_noise(0.004, seed=3), library)
    truth = compare_to_truth(refined, system, clean)
    assert truth.exact_support, (truth.missing, truth.spurious, str(refined))
    assert truth.max_error() < 1e-3, _errors(truth)
    model = identify(clean.with_noise(0.004, seed=3), library, refine=False)
    truth = compare_to_truth(model, system, clean)
    assert truth.missing == {"x1": [], "x2": ["sin(x1)"]} and truth.spurious == {"x1": [], "x2": ["x1"]}
    kept = {t.name: t for t in model.equation("x2").terms}
    assert set(kept) == {"F", "x1", "x2"}
    assert "sin(x1)" in kept["x1"].alternatives
    assert kept["x1"].coef == pytest.approx(-9.81, rel=0.01)


# --- cubic stiffness and Coulomb friction together ---------------------------------------------


def duffing_coulomb(kc: float, m=1.0, c=20.0, k=1e4, k3=1e9) -> OdeSystem:
    """``m x1'' + c x1' + k x1 + k3 x1**3 + kc sign(x1') = F`` with the paper's m, c, k and Duffing k3."""
    x1, x2, F = symbols("x1 x2 F")
    pm, pc, pk, pk3, pkc = symbols("m c k k3 kc")
    return OdeSystem(
        states=(x1, x2),
        inputs=(F,),
        rhs=(x2, (F - pc * x2 - pk * x1 - pk3 * x1**3 - pkc * ca.sign(x2)) / pm),
        parameters=(pm, pc, pk, pk3, pkc),
        parameter_values=(m, c, k, k3, kc),
        name="duffing_coulomb",
    )


@cache
def _duffing_coulomb_record(kc: float, forcing: str, seed: int):
    signal = Sine(100.0, 10.0) if forcing == "sine" else Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=10 + seed)
    return simulate(duffing_coulomb(kc), time_grid(1.0, FS), inputs=signal)


@pytest.mark.slow
@pytest.mark.parametrize("kc, forcing", [(1.0, "sine"), (5.0, "sine"), (10.0, "multisine")])
def test_cubic_stiffness_with_coulomb_friction(kc, forcing):
    """Both nonlinearities at once, 1 s at 32768 Hz, 0.4 % noise, Eq. 21 to degree 5, seeds 0-4:
    exact support; every coefficient within 5 % (largest seen: 3.3 % for sign(x2) at kc = 1 N,
    where friction carries 0.008 % of the variance; 1.9 % at kc = 10 N), and within 1 % for
    the terms carrying >= 5 % of the variance. At kc = 10 N under the 10 Hz sine, 3 of 20 seeds
    fail: seeds 4 and 15 add x2*|x2| (-2.4 +- 0.5 and -3.1 +- 0.6), which the evidence prefers to
    the true support by 1.6 nats (noise-free data give the exact model, so noise on the velocity,
    which blurs sign(x2) near its zero crossings, is the likely cause); seed 17 is the search
    failure below. The broadband multisine gives exact supports."""
    system = duffing_coulomb(kc)
    library = paper(system.states, system.inputs, degree=5)
    for seed in range(5):
        clean = _duffing_coulomb_record(kc, forcing, seed)
        model = identify(clean.with_noise(0.004, seed=seed), library, refine=False)  # as measured above
        truth = compare_to_truth(model, system, clean)
        assert truth.exact_support, (seed, truth.missing, truth.spurious, str(model))
        assert truth.max_error() < 0.05, (seed, _errors(truth))
        assert truth.max_error(min_share=0.05) < 0.01, (seed, _errors(truth))


@pytest.mark.slow
def test_cubic_stiffness_with_strong_coulomb_friction_under_a_sine():
    """kc = 10 N under the 10 Hz sine, noise seed 17: the first RVM pass settles among look-alikes
    (x1|x1|, x1**3|x1|, sign(x1), ...; penalised log evidence -78.5 against -73.5 for the truth);
    the multi-start support search must still reach the true equations. The narrow ``tanh`` fitted for
    ``sign`` leaves innovations the Ljung-Box test sees (p = 1e-4), but their past predicts 0.18 % of their
    variance, below the colour that matters (0.5 %): no doubt, and the output error's model is reported, its
    friction force within 0.1 %."""
    system = duffing_coulomb(10.0)
    clean = _duffing_coulomb_record(10.0, "sine", 0)
    model = identify(clean.with_noise(0.004, seed=17), paper(system.states, system.inputs, degree=5))
    truth = compare_to_truth(model, system, clean)
    assert truth.exact_support, (truth.missing, truth.spurious, str(model))
    info = model.metadata["refine"]
    assert model.metadata["estimator"]["used"] == "output-error" and not info["doubts"]
    assert min(t["whiteness_p"] for t in info["residual"]) < 0.01  # the test sees the colour ...
    assert max(t["predictable"] for t in info["residual"]) < 0.005  # ... and it does not matter
    assert model.equation("x2").coef("sign(x2)") == pytest.approx(-10.0, rel=1e-3)


# --- free decay: no input, no input terms -------------------------------------------------------


def free_duffing(c=20.0, k=1e4, k3=1e9) -> OdeSystem:
    """The paper's Duffing oscillator without an input: ``x1'' + c x1' + k x1 + k3 x1**3 = 0``."""
    x1, x2 = symbols("x1 x2")
    pc, pk, pk3 = symbols("c k k3")
    return OdeSystem(
        states=(x1, x2),
        inputs=(),
        rhs=(x2, -pc * x2 - pk * x1 - pk3 * x1**3),
        parameters=(pc, pk, pk3),
        parameter_values=(c, k, k3),
        name="free_duffing",
    )


@pytest.mark.slow
def test_free_decay_without_input():
    """Released from x1 = 10 mm at rest (k3 x1**3 is then ten times k x1), 0.3 s at 32768 Hz
    (seven and a half cycles, amplitude down to 1.3 mm), 0.4 % noise, seeds 0-4: the library has no
    input column and the model no input; exact support; every coefficient within 4 posterior
    standard deviations (largest |z| seen 1.7) and within 10 % (largest seen 7.0 %, the damping:
    a decaying record carries far less information than a forced one)."""
    system = free_duffing()
    library = paper(system.states, degree=5)
    assert library.variable_names == ["x1", "x2"] and "F" not in [t.name for t in library]
    clean = simulate(system, time_grid(0.3, FS), inputs=None, x0=[0.01, 0.0])
    assert clean.input_names == () and clean.inputs.shape == (clean.n_samples, 0)
    truth_coefs = {"x1": {"x2": 1.0}, "x2": {"x2": -20.0, "x1": -1e4, "x1**3": -1e9}}
    for seed in range(5):
        model = identify(clean.with_noise(0.004, seed=seed), library)
        assert len(model.input_names) == 0
        truth = compare_to_truth(model, system, clean)
        assert truth.exact_support, (seed, truth.missing, truth.spurious, str(model))
        assert truth.max_error() < 0.10, (seed, _errors(truth))
        _assert_within_posterior(model, truth_coefs, 4.0)


# --- Lorenz with a polynomial library -----------------------------------------------------------


@pytest.mark.slow
def test_lorenz_with_polynomial_library():
    """Lorenz (sigma 10, rho 28, beta 8/3) from (-8, 7, 27): 10 s at 1 kHz (the orbit turns at
    about 1.35 Hz, so ~740 samples per turn and a dozen turns over both wings; x, y within
    +-22, z in 8-43), 0.4 % noise, all 20 monomials of (x, y, z) to degree 3, seeds 0-2: exact
    support; coefficients within 0.5 % for the terms carrying >= 5 % of the variance and 5 %
    for all (largest seen 2.3 %, the -y of y', 0.08 % of its equation's variance)."""
    system = systems.lorenz()
    assert dict(zip(system.parameter_names, system.parameter_values)) == pytest.approx(
        {"sigma": 10.0, "rho": 28.0, "beta": 8.0 / 3.0}
    )
    clean = simulate(system, time_grid(10.0, 1000.0), x0=[-8.0, 7.0, 27.0])
    assert np.all(np.ptp(clean.states, axis=0) > 30)
    library = polynomial(system.states, 3)
    assert len(library) == 20
    for seed in range(3):
        with pytest.warns(RefineWarning, match="the record is hypersensitive"):  # chaotic: said so
            model = identify(clean.with_noise(0.004, seed=seed), library)
        assert model.metadata["refine"]["hypersensitive"]
        truth = compare_to_truth(model, system, clean)
        assert truth.exact_support, (seed, truth.missing, truth.spurious, str(model))
        assert truth.max_error(min_share=0.05) < 0.005, (seed, _errors(truth))
        assert truth.max_error() < 0.05, (seed, _errors(truth))


# --- noise beyond 0.4 % on the paper's five systems ---------------------------------------------


@cache
def _paper_record(name: str, duration: float = 2.0):
    build, kwargs = CASES[name]
    system = build(**kwargs)
    return system, simulate(system, time_grid(duration, FS), inputs=Sine(100.0, 10.0))


#: noise level -> (bound on terms with >= 5 % of the variance, bound on all terms); see the module docstring.
NOISE_TOLERANCES = {0.01: (0.01, 0.25), 0.02: (0.03, 0.40)}


@pytest.mark.slow
@pytest.mark.parametrize("level", sorted(NOISE_TOLERANCES))
@pytest.mark.parametrize("name", list(CASES))
def test_paper_systems_at_higher_noise(name, level):
    """1 % and 2 % noise, otherwise the paper's settings (2 s, degree 6, 4 for Bouc-Wen), seeds
    0-2: exact support, coefficient errors within the bounds of NOISE_TOLERANCES."""
    system, clean = _paper_record(name)
    library = paper(system.states, system.inputs, degree=4 if name.startswith("Bouc") else 6)
    big, every = NOISE_TOLERANCES[level]
    for seed in range(3):
        model = identify(clean.with_noise(level, seed=seed), library, refine=False)  # as measured above
        truth = compare_to_truth(model, system, clean)
        assert truth.exact_support, (seed, truth.missing, truth.spurious, str(model))
        assert truth.max_error(min_share=0.05) < big, (seed, _errors(truth))
        assert truth.max_error() < every, (seed, _errors(truth))


def _clean_window(name: str) -> int:
    """The weak-form window the automatic rule picks on the noise-free record (315 for linear)."""
    system, clean = _paper_record(name)
    library = paper(system.states, system.inputs, degree=6)
    return WeakForm().resolve(clean.t, clean.states, n_terms=len(library)).window


def test_weak_window_is_set_by_the_signal_not_the_noise():
    """At 5 % noise the automatic window should stay near the one chosen on noise-free data."""
    system, clean = _paper_record("linear")
    n_terms = len(paper(system.states, system.inputs, degree=6))
    noisy = WeakForm().resolve(clean.t, clean.with_noise(0.05, seed=0).states, n_terms=n_terms).window
    assert noisy >= _clean_window("linear") / 2


def _linear_at_five_percent(derivative):
    system, clean = _paper_record("linear")
    model = identify(
        clean.with_noise(0.05, seed=0), paper(system.states, system.inputs, degree=6), derivative=derivative
    )
    return compare_to_truth(model, system, clean), model


@pytest.mark.slow
def test_five_percent_noise_linear_oscillator():
    """The linear oscillator at 5 % noise with default options should be recovered exactly."""
    truth, model = _linear_at_five_percent("weak")
    assert truth.exact_support, (truth.missing, truth.spurious, str(model))


@pytest.mark.slow
def test_five_percent_noise_is_not_beyond_the_data():
    """With the weak-form window the automatic rule picks on noise-free data, the same 5 %-noise
    record gives the exact linear oscillator (coefficients within 2 %): the automatic window (chosen
    above the noise floor) and this one agree."""
    truth, model = _linear_at_five_percent(WeakForm(window=_clean_window("linear")))
    assert truth.exact_support, (truth.missing, truth.spurious, str(model))
    assert truth.max_error() < 0.02, _errors(truth)
