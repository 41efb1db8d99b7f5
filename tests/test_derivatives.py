"""Derivative strategies reach their stated order; the weak form is exact for linear operators."""

import numpy as np
import pytest
from helpers import exactly

from symsbl import DataError, ParameterError
from symsbl._derivatives.registry import (
    CentralDifference,
    PointDifference,
    SavitzkyGolay,
    WeakForm,
    get_differentiator,
)

OMEGA = 2 * np.pi * 3.0


def _signal(n):
    t = np.linspace(0.0, 1.0, n + 1)
    x = np.column_stack([np.sin(OMEGA * t), np.cos(2 * OMEGA * t) + t**2])
    dx = np.column_stack([OMEGA * np.cos(OMEGA * t), -2 * OMEGA * np.sin(2 * OMEGA * t) + 2 * t])
    return t, x, dx


def _pointwise_error(strategy, n):
    t, x, dx = _signal(n)
    d = strategy.targets(t, x)
    inner = slice(10, -10)  # interior points, where the stated order applies
    return np.max(np.abs(d[inner] - dx[inner]))


@pytest.mark.parametrize(
    "strategy",
    [
        PointDifference(),
        CentralDifference(),
        SavitzkyGolay(window=7, polyorder=3),
        SavitzkyGolay(window=9, polyorder=4),
    ],
)
def test_pointwise_order(strategy):
    ns = np.array([400, 800, 1600])
    errs = np.array([_pointwise_error(strategy, n) for n in ns])
    slope = -np.polyfit(np.log(ns), np.log(errs), 1)[0]
    assert slope == pytest.approx(strategy.order, abs=0.25)


def test_point_difference_is_the_forward_difference():
    t = np.arange(5) * 0.5
    x = np.array([0.0, 1.0, 3.0, 6.0, 10.0])
    np.testing.assert_allclose(PointDifference().targets(t, x)[:, 0], [2, 4, 6, 8, 8])


def test_weak_form_matches_exact_integral():
    # target = int phi x' / int phi must equal reduce(x') for any x, to quadrature accuracy
    t, x, dx = _signal(4000)
    wf = WeakForm(window=40, power=4)
    np.testing.assert_allclose(wf.targets(t, x), wf.reduce(dx), rtol=0, atol=2e-6)
    assert wf.targets(t, x).shape == (wf.n_rows(len(t)), 2)


def test_weak_form_quadrature_order():
    # fixed physical window (1/20 s), shrinking sample interval: error falls at >= order 2p
    errs = []
    ns = [400, 800, 1600]
    for n in ns:
        t, x, dx = _signal(n)
        wf = WeakForm(window=n // 20, power=4)
        # reference: window averages of x' by a fine quadrature of the same test functions
        fine = 64
        tf, xf, dxf = _signal(n * fine)
        ref = WeakForm(window=n // 20 * fine, power=4).reduce(dxf)
        errs.append(np.max(np.abs(wf.targets(t, x) - ref)))
    slope = -np.polyfit(np.log(ns), np.log(errs), 1)[0]
    assert slope == pytest.approx(WeakForm(power=4).order, abs=0.3)
    assert errs[-1] < 5e-6


def test_weak_form_is_linear_in_the_dictionary():
    rng = np.random.default_rng(0)
    D = rng.standard_normal((1001, 3))
    beta = np.array([1.5, -2.0, 0.25])
    wf = WeakForm(window=25)
    np.testing.assert_allclose(wf.reduce(D @ beta)[:, 0], wf.reduce(D) @ beta, rtol=1e-12)


def test_weak_form_rows_have_independent_noise():
    # non-overlapping windows: rows of pure white noise are uncorrelated
    rng = np.random.default_rng(1)
    t = np.arange(200_001) * 1e-3
    e = rng.standard_normal((len(t), 1))
    r = WeakForm(window=20).targets(t, e)[:, 0]
    rho = np.corrcoef(r[:-1], r[1:])[0, 1]
    assert abs(rho) < 4 / np.sqrt(len(r))


@pytest.mark.parametrize("overlap", [2, 3])
def test_overlapping_windows_give_the_generalised_least_squares_statistics(overlap):
    # Brute force: the unwhitened rows as dense operators on the samples, the rows' noise covariance
    # W W^T of white noise in x, and D^T C^-1 D, D^T C^-1 y with that covariance (scaled to a unit
    # diagonal) against the whitened rows' sums of products.
    rng = np.random.default_rng(3)
    n, window = 400, 12
    t = np.arange(n) * 1e-3
    x = np.cumsum(rng.standard_normal(n))[:, None] * 1e-2
    D = np.column_stack([x[:, 0], x[:, 0] ** 3, np.sin(40 * t)])
    weak = WeakForm(window=window, overlap=overlap)
    phi, dphi = weak._weights(t[1] - t[0])
    rows = weak.n_rows(n)
    Wt, Wd = np.zeros((rows, n)), np.zeros((rows, n))
    for j in range(rows):
        a = j * weak.stride
        Wt[j, a : a + window + 1], Wd[j, a : a + window + 1] = -dphi, phi
    C = Wt @ Wt.T
    C /= C[0, 0]
    y_ref, D_ref = Wt @ x, Wd @ D
    y, R = weak.targets(t, x), weak.reduce(D)
    np.testing.assert_allclose(R.T @ R, D_ref.T @ np.linalg.solve(C, D_ref), rtol=1e-9)
    np.testing.assert_allclose(R.T @ y, D_ref.T @ np.linalg.solve(C, y_ref), rtol=1e-9)
    np.testing.assert_allclose(y.T @ y, y_ref.T @ np.linalg.solve(C, y_ref), rtol=1e-9)


def test_whitened_rows_of_white_noise_are_white():
    rng = np.random.default_rng(4)
    t = np.arange(200_001) * 1e-3
    weak = WeakForm(window=20, overlap=2)
    e = rng.standard_normal((len(t), 1))
    r = weak.targets(t, e)[:, 0]
    raw = -np.einsum("k,jkc->jc", weak._weights(1e-3)[1], weak._windows(e))[:, 0]
    assert np.corrcoef(raw[:-1], raw[1:])[0, 1] < -0.2  # half-overlapping rows share noise ...
    for lag in (1, 2, 3):  # ... which the whitening removes
        assert abs(np.corrcoef(r[:-lag], r[lag:])[0, 1]) < 4 / np.sqrt(len(r))


def test_registry_and_errors():
    assert isinstance(get_differentiator("central"), CentralDifference)
    with pytest.raises(
        ValueError,
        match=exactly("derivative: expected one of ['weak', 'central', 'point', 'savgol'], received 'spline'"),
    ):
        get_differentiator("spline")
    with pytest.raises(
        DataError,
        match=exactly(
            "X: expected at least 33 samples for this differentiator, received 10; "
            "use a longer record or a shorter window"
        ),
    ):
        WeakForm(window=32).targets(np.arange(10.0), np.zeros(10))
    with pytest.raises(
        ParameterError,
        match=exactly("SavitzkyGolay.window: expected an odd number greater than polyorder=3, received 8"),
    ):
        SavitzkyGolay(window=8).targets(np.arange(10.0), np.zeros(10))


@pytest.mark.parametrize(
    "strategy", [PointDifference(), CentralDifference(), WeakForm(window=16), WeakForm(window=16, overlap=2)]
)
def test_reduce_in_blocks_equals_reduce_at_once(strategy):
    rng = np.random.default_rng(2)
    D = rng.standard_normal((1000, 3))
    whole = strategy.reduce(D)
    n = strategy.n_rows(len(D))
    blocks = []
    for r0 in range(0, n, 7):
        r1 = min(r0 + 7, n)
        s0, s1 = strategy.sample_span(r0, r1)
        blocks.append(strategy.reduce(D[s0:s1])[-(r1 - r0) :])
    # the same sums, but BLAS may order them differently for a block's shape than for the
    # whole record's (seen on one CPU: differences of one unit in the last place)
    np.testing.assert_allclose(np.vstack(blocks), whole[:n], rtol=1e-13, atol=1e-14)


def test_weak_form_automatic_window_follows_the_bandwidth():
    # a 10 Hz sine sampled at 4096 Hz: f_hi = 10 Hz -> window 0.5 / 10 s = 205 samples
    t = np.arange(40_961) / 4096.0
    x = np.sin(2 * np.pi * 10 * t)[:, None]
    wf = WeakForm().resolve(t, x)
    assert wf.window == round(0.5 / 10 * 4096)
    # at most n / (2 n_terms) samples per window, so there are enough rows for the terms
    assert WeakForm().resolve(t, x, n_terms=200).window == (len(t) - 1) // 400
    assert WeakForm(window=16).resolve(t, x) == WeakForm(window=16)
    with pytest.raises(
        ParameterError,
        match=exactly("WeakForm.window: expected a window resolved from data (call resolve(t, X)), received None"),
    ):
        WeakForm().targets(t, x)


def test_a_servo_axis_velocity_from_its_encoder_matches_the_benchmark_recipe():
    """12 s of the EMPS axis's encoder (tests/data/emps_slice.npz; a position whose power falls steeply with
    frequency, 5e-8 m steps): the smoothing derivative over the velocity's own band is within 0.5 % (RMS) of
    the benchmark's recipe (a zero-phase 4th-order Butterworth at 100 Hz, then central differences); over the
    position's band (0.5 Hz on the whole record) it was 16 % off there. Its noise (the encoder's quantisation
    through the filter) is far below the 1e-3 of the velocity's spread at which identify reports the equation
    error on it."""
    from pathlib import Path

    import scipy.signal

    from symsbl._derivatives.kinematics import estimate_velocity, velocity_noise

    d = np.load(Path(__file__).parent / "data" / "emps_slice.npz")
    t, q = d["t"], d["qm"]
    b, a = scipy.signal.butter(4, 100.0 / 500.0)
    recipe = np.gradient(scipy.signal.filtfilt(b, a, q), t)
    v = estimate_velocity(t, q)
    inner = slice(200, -200)
    assert np.std(v[inner] - recipe[inner]) < 0.005 * np.std(recipe), np.std(v - recipe) / np.std(recipe)
    assert velocity_noise(t, q, v) < 1e-4


def test_velocity_noise_is_the_spread_of_the_estimate_on_noise_alone():
    """A 2-8 Hz multisine position with white noise of 1e-3 (1 kHz, 3 seeds): :func:`velocity_noise` is within
    10 % of the RMS difference between the estimate from the noisy position and the same filter applied to the
    clean one (brute force), over the estimate's spread."""
    import scipy.signal

    from symsbl._derivatives.kinematics import _half_window, estimate_velocity, velocity_noise

    t = np.arange(16000) / 1000.0
    for seed in range(3):
        rng = np.random.default_rng(seed)
        clean = sum(np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)) for f in (2.0, 3.5, 5.0, 8.0))
        x = clean + 1e-3 * rng.standard_normal(t.size)
        v = estimate_velocity(t, x)
        h, half = _half_window(t, x)
        filtered = scipy.signal.savgol_filter(clean, 2 * half + 1, 5, deriv=1, delta=h, mode="interp")
        brute = np.std((v - filtered)[half:-half]) / np.std(v)
        assert velocity_noise(t, x, v) == pytest.approx(brute, rel=0.1), (velocity_noise(t, x, v), brute)


def test_slow_motion_sampled_fast_keeps_its_velocity():
    """Slow motion sampled fast, where the widest windows are weighed (a 0.2 Hz sine at 1 kHz with 3 % noise; a
    0.5-2 Hz multisine at 10 kHz with 1 %): the estimate is within 1.5 % (RMS) of the true velocity, and the
    widest half-window's quintic coefficients still hold the derivative (scipy's lose it to rounding from 997
    samples, where a velocity of zero came out, its noise read as 1e-13)."""
    import scipy.signal

    from symsbl._derivatives.kinematics import MAX_HALF, estimate_velocity

    c = scipy.signal.savgol_coeffs(2 * MAX_HALF + 1, 5, deriv=1, use="dot")
    assert c @ np.arange(-MAX_HALF, MAX_HALF + 1) == pytest.approx(1.0, rel=1e-4)  # 1 - 2.4e-6; 0 from 997
    for fs, seconds, freqs, noise in ((1000.0, 20.0, (0.2,), 0.03), (10000.0, 20.0, (0.5, 1.0, 2.0), 0.01)):
        t = np.arange(int(seconds * fs)) / fs
        x = sum(np.sin(2 * np.pi * f * t) for f in freqs)
        v = sum(2 * np.pi * f * np.cos(2 * np.pi * f * t) for f in freqs)
        noisy = x + noise * np.std(x) * np.random.default_rng(0).standard_normal(t.size)
        assert np.std(estimate_velocity(t, noisy) - v) < 0.015 * np.std(v), (fs, freqs)
