"""Simulation against exact solutions (matrix exponentials), convergence orders and cross-method agreement."""

import os
import shutil
import signal
import threading
import time

import casadi as ca
import numpy as np
import pytest
from helpers import exactly
from scipy.linalg import expm

from symsbl import (
    DataError,
    FreeDecay,
    OdeSystem,
    Sampled,
    SimulationError,
    Sine,
    simulate,
    systems,
    time_grid,
)

M, C, K = 1.0, 20.0, 1e4
A_LIN = np.array([[0.0, 1.0], [-K / M, -C / M]])
FS = 32768


def rel_err(x, ref):
    """Largest error of each state relative to that state's peak."""
    return np.max(np.abs(x - ref) / np.abs(ref).max(axis=0))


def exact_linear(t, x0, generator, g0, gain):
    """Exact response of the linear oscillator driven by ``u = gain @ g`` with ``g' = generator @ g``.

    The augmented system ``[x; g]' = [[A, b gain], [0, generator]] [x; g]`` is linear and autonomous, so
    its solution is ``expm(M t) [x0; g0]``.
    """
    n = generator.shape[0]
    Maug = np.zeros((2 + n, 2 + n))
    Maug[:2, :2] = A_LIN
    Maug[1, 2:] = np.asarray(gain) / M
    Maug[2:, 2:] = generator
    z0 = np.concatenate([x0, g0])
    return np.array([(expm(Maug * (tk - t[0])) @ z0)[:2] for tk in t])


def sine_reference(t, x0, amp, freq, phase):
    w = 2 * np.pi * freq
    gen = np.array([[0.0, w], [-w, 0.0]])  # s = sin(w t + phase), c = cos(w t + phase)
    return exact_linear(t, x0, gen, [np.sin(w * t[0] + phase), np.cos(w * t[0] + phase)], [amp, 0.0])


def ramp_reference(t, x0, slope, offset):
    gen = np.array([[0.0, slope], [0.0, 0.0]])  # r = offset + slope t, one = 1
    return exact_linear(t, x0, gen, [offset + slope * t[0], 1.0], [1.0, 0.0])


EVERY = slice(None, None, 331)  # the matrix-exponential reference on ~100 of the samples


@pytest.mark.parametrize("method", ["cvodes", "rk4"])
def test_linear_free_decay_matches_matrix_exponential(method):
    t = time_grid(1.0, FS)
    x0 = np.array([0.01, -0.3])
    tr = simulate(systems.linear(), t, inputs=FreeDecay(), x0=x0, method=method, jit=False)
    ref = np.array([expm(A_LIN * tk) @ x0 for tk in t[EVERY]])
    assert rel_err(tr.states[EVERY], ref) < 1e-8
    np.testing.assert_array_equal(tr.inputs, 0.0)
    assert tr.state_names == ("x1", "x2") and tr.input_names == ("F",) and tr.diverged_at is None


@pytest.mark.parametrize("method", ["cvodes", "rk4"])
def test_linear_sine_matches_augmented_matrix_exponential(method):
    t = time_grid(1.0, FS)
    sig = Sine(amplitude=100.0, frequency=10.0, phase=0.4)
    tr = simulate(systems.linear(), t, inputs=sig, x0=[1e-3, 0.0], method=method, jit=False)
    ref = sine_reference(t[EVERY], np.array([1e-3, 0.0]), 100.0, 10.0, 0.4)
    assert rel_err(tr.states[EVERY], ref) < 1e-8
    np.testing.assert_allclose(tr.inputs[:, 0], sig(t), rtol=0, atol=1e-12)


@pytest.mark.parametrize("method", ["cvodes", "rk4"])
def test_sampled_input_is_held_linear(method):
    """A ramp is represented exactly by linear interpolation: sampled = exact, on and off the sample grid."""
    t = time_grid(0.5, 4096)
    x0 = np.array([0.0, 0.1])
    ref = ramp_reference(t[::41], x0, slope=300.0, offset=-20.0)
    kw = dict(method=method, jit=False, rtol=1e-11, substeps=4)
    on_grid = simulate(systems.linear(), t, inputs=300.0 * t - 20.0, x0=x0, **kw)
    assert rel_err(on_grid.states[::41], ref) < 1e-8
    coarse = np.linspace(0, 0.5, 501)  # a measured input at 1 kHz, simulated at 4096 Hz
    off_grid = simulate(systems.linear(), t, inputs=Sampled(coarse, 300.0 * coarse - 20.0), x0=x0, **kw)
    assert rel_err(off_grid.states[::41], ref) < 1e-8


def test_rk4_converges_at_fourth_order():
    t = time_grid(0.5, 256)
    ref = sine_reference(t, np.zeros(2), 100.0, 10.0, 0.0)
    errs = [
        rel_err(simulate(systems.linear(), t, inputs=Sine(), method="rk4", substeps=s, jit=False).states, ref)
        for s in (1, 2, 4, 8)
    ]
    slope = -np.polyfit(np.log([1, 2, 4, 8]), np.log(errs), 1)[0]
    assert 3.8 < slope < 4.2, errs


def test_coulomb_rk4_converges_first_order_and_auto_avoids_cvodes():
    s = systems.coulomb()
    t = time_grid(0.5, 4096)
    auto = simulate(s, t, inputs=Sine(), jit=False)
    np.testing.assert_array_equal(auto.states, simulate(s, t, inputs=Sine(), method="rk4", jit=False).states)
    ref = simulate(s, t, inputs=Sine(), method="rk4", substeps=128, jit=False).states
    subs = [1, 2, 4, 8]
    errs = [rel_err(simulate(s, t, inputs=Sine(), method="rk4", substeps=n, jit=False).states, ref) for n in subs]
    slope = -np.polyfit(np.log(subs), np.log(errs), 1)[0]
    assert 0.7 < slope < 1.5, errs  # first order: the sign switches cost an O(h**2) local error each
    assert errs[0] < 3e-4


def test_coulomb_stalls_cvodes_which_reports_it():
    t = time_grid(0.1, 4096)
    with pytest.raises(
        SimulationError,
        match=exactly(
            "simulation of 'coulomb' with cvodes: expected a solution that "
            "stays finite, received divergence at t = 0 s (cvodes failed: "
            'CVode returned "CV_TOO_MUCH_WORK". Consult CVODES '
            "documentation.); fewer than 2 samples were computed, so there "
            "is nothing to return; the right-hand side is discontinuous: use "
            "method='rk4' (or 'auto')"
        ),
    ):
        simulate(systems.coulomb(), t, inputs=Sine(), method="cvodes")


def test_ctrl_c_inside_cvodes_is_an_interrupt_not_a_divergence(capsys):
    """CVODES polls for Ctrl-C in its callbacks and reports it as CV_RHSFUNC_FAIL: it must stay an interrupt."""
    t = time_grid(40.0, FS)  # 20 segments of CVODES
    t0 = time.perf_counter()
    simulate(systems.duffing(), t, inputs=Sine(), method="cvodes")
    whole = time.perf_counter() - t0
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer = threading.Timer(whole / 2, lambda: os.kill(os.getpid(), signal.SIGINT))  # mid-run: inside CVODES
    t0 = time.perf_counter()
    try:
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            simulate(systems.duffing(), t, inputs=Sine(), method="cvodes")
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, previous)
    assert time.perf_counter() - t0 < whole
    assert capsys.readouterr().err == ""  # CasADi's "rhs failed: KeyboardInterrupt" is not shown


def test_duffing_rk4_and_cvodes_agree():
    t = time_grid(1.0, FS)
    rk4 = simulate(systems.duffing(), t, inputs=Sine(), method="rk4", substeps=2, jit=False)
    cv = simulate(systems.duffing(), t, inputs=Sine(), method="cvodes")
    assert rel_err(rk4.states, cv.states) < 1e-7
    assert np.abs(cv.states[:, 0]).max() == pytest.approx(6.3e-3, rel=0.01)  # the notes' Duffing amplitude


@pytest.mark.parametrize("n", [2, 3])
def test_bouc_wen_runs_and_methods_agree(n):
    """abs() only puts kinks in the right-hand side: "auto" keeps cvodes, and RK4 converges towards it."""
    t = time_grid(0.5, FS)
    s = systems.bouc_wen(n=n)
    cv = simulate(s, t, inputs=Sine())
    np.testing.assert_array_equal(cv.states, simulate(s, t, inputs=Sine(), method="cvodes").states)
    errs = [
        rel_err(simulate(s, t, inputs=Sine(), method="rk4", substeps=k, jit=False).states, cv.states) for k in (1, 4)
    ]
    assert errs[1] < 5e-6 and errs[1] < errs[0] / 3
    assert np.abs(cv.states[:, 2]).max() > 10.0  # the hysteretic force is active


def blow_up():
    x = ca.SX.sym("x")
    return OdeSystem((x,), (), (x**2,), name="blow_up")  # x(t) = 1 / (1 - t) from x(0) = 1


@pytest.mark.parametrize("method", ["cvodes", "rk4"])
def test_divergence_raises_or_truncates(method):
    t = time_grid(2.0, 1000)
    with pytest.raises(
        SimulationError,
        match=rf"^simulation of 'blow_up' with {method}: expected a solution that "
        rf"stays "
        r"finite, received divergence at t = (1\.\d+|0\.99\d+) s \(.+\); pass "
        r"on_divergence='truncate' to get the trajectory up to that point$",
    ):
        simulate(blow_up(), t, x0=[1.0], method=method, jit=False)
    for mode in ("truncate", "return"):
        tr = simulate(blow_up(), t, x0=[1.0], method=method, on_divergence=mode, jit=False)
        assert 0.95 < tr.diverged_at < 1.05 and tr.t[-1] <= tr.diverged_at
        assert np.all(np.isfinite(tr.states)) and tr.n_samples > 900
        np.testing.assert_allclose(tr.states[:500, 0], 1 / (1 - tr.t[:500]), rtol=1e-6)


def test_chunks_carry_the_state_and_start_time_is_absolute():
    s = systems.duffing()
    t = time_grid(0.2, 8192)
    whole = simulate(s, t, inputs=Sine(), method="rk4", jit=False)
    np.testing.assert_array_equal(
        simulate(s, t, inputs=Sine(), method="rk4", chunk_size=7, jit=False).states, whole.states
    )
    for method in ("rk4", "cvodes"):
        whole = simulate(s, t, inputs=Sine(), method=method, jit=False)
        tail = simulate(s, t[500:], inputs=Sine(), x0=whole.states[500], method=method, jit=False)
        assert rel_err(tail.states, whole.states[500:]) < 1e-8


@pytest.mark.parametrize("method", ["cvodes", "rk4"])
def test_reparameterised_system_matches_fresh_one(method):
    t = time_grid(0.2, 8192)
    moved = simulate(systems.duffing().with_parameters(k3=3e9, c=5.0), t, inputs=Sine(), method=method, jit=False)
    fresh = simulate(systems.duffing(k3=3e9, c=5.0), t, inputs=Sine(), method=method, jit=False)
    np.testing.assert_allclose(moved.states, fresh.states, rtol=0, atol=1e-15)
    other = simulate(systems.duffing(), t, inputs=Sine(), method=method, jit=False)
    assert rel_err(moved.states, other.states) > 1e-2


def test_two_inputs_analytic_and_sampled():
    x1, x2, u1, u2 = (ca.SX.sym(n) for n in ("x1", "x2", "u1", "u2"))
    s = OdeSystem((x1, x2), (u1, u2), (x2, -400 * x1 - 4 * x2 + u1 + 0.5 * u2), name="two_inputs")
    t = time_grid(1.0, 2048)
    inputs = [Sine(3.0, 5.0), Sampled(t, np.cos(2 * np.pi * 2 * t))]
    rk4 = simulate(s, t, inputs=inputs, method="rk4", substeps=4, jit=False)
    cv = simulate(s, t, inputs=inputs, method="cvodes")
    assert rel_err(rk4.states, cv.states) < 1e-7
    np.testing.assert_allclose(rk4.inputs, np.column_stack([inputs[0](t), inputs[1](t)]), atol=1e-12)


def test_system_without_inputs():
    t = time_grid(0.5, 1000)
    tr = simulate(systems.lorenz(), t, x0=[1.0, 1.0, 1.0])
    rk4 = simulate(systems.lorenz(), t, x0=[1.0, 1.0, 1.0], method="rk4", substeps=4, jit=False)
    assert tr.inputs.shape == (t.size, 0) and rel_err(rk4.states, tr.states) < 1e-6


@pytest.mark.skipif(not (shutil.which("gcc") or shutil.which("cc")), reason="no C compiler for JIT")
def test_jit_matches_virtual_machine():
    t = time_grid(0.25, FS)
    vm = simulate(systems.coulomb(), t, inputs=Sine(), method="rk4", jit=False)
    jit = simulate(systems.coulomb(), t, inputs=Sine(), method="rk4", jit=True)
    assert rel_err(jit.states, vm.states) < 1e-12


def test_argument_errors():
    s, t = systems.linear(), time_grid(0.01, 1000)
    with pytest.raises(
        SimulationError, match=exactly("method: expected one of 'auto', 'cvodes', 'rk4', received 'euler'")
    ):
        simulate(s, t, method="euler")
    with pytest.raises(
        SimulationError, match=exactly("on_divergence: expected one of 'raise', 'truncate', received 'x'")
    ):
        simulate(s, t, on_divergence="x")
    with pytest.raises(SimulationError, match=exactly("jit: expected one of 'auto', True, False, received 'yes'")):
        simulate(s, t, jit="yes")
    with pytest.raises(
        SimulationError, match=exactly("x0: expected 2 finite values (states ['x1', 'x2']), received array([1.])")
    ):
        simulate(s, t, x0=[1.0])
    with pytest.raises(
        SimulationError,
        match=exactly(
            "inputs: expected one signal per input of 'linear' ['F'], "
            "received signals for 2; use FreeDecay() for a zero input"
        ),
    ):
        simulate(s, t, inputs=[Sine(), Sine()])
    with pytest.raises(
        SimulationError,
        match=exactly("inputs: expected an array sampled on t: shape (11,) or (11, 1), received shape (5,)"),
    ):
        simulate(s, t, inputs=np.zeros(5))
    with pytest.raises(
        SimulationError,
        match=exactly(
            "t: expected a grid inside the sampled input's span [0.0, "
            "0.005], "
            "received [0.0, 0.01]; shorten t or supply samples covering it"
        ),
    ):
        simulate(s, t, inputs=Sampled([0.0, 0.005], [1.0, 2.0]))
    with pytest.raises(SimulationError, match=exactly("substeps: expected an integer >= 1, received 0")):
        simulate(s, t, method="rk4", substeps=0)
    with pytest.raises(SimulationError, match=exactly("inputs: expected Signals or an array, received an element 'F'")):
        simulate(s, t, inputs=[Sine(), "F"])
    with pytest.raises(SimulationError, match=exactly("system: expected an OdeSystem, received str")):
        simulate("duffing", t)
    with pytest.raises(
        SimulationError, match=exactly("duration * fs: expected at least 1 sample interval, received 0.0 s at 1000 Hz")
    ):
        time_grid(0.0, 1000)
    with pytest.raises(
        DataError,
        match=exactly(
            "time: expected strictly increasing values, received t = 0.009 at row "
            "1 after t = 0.01; sort the rows or pass --fs/fs for a rounded time "
            "column"
        ),
    ):
        simulate(s, t[::-1])
