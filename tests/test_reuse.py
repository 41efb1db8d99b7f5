"""Compiled passes shared by structures: a sub-structure fitted on its host's passes, checked against its own."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import symsbl
from symsbl import Multisine, identify, refine, simulate, time_grid
from symsbl._base import jit as jit_module
from symsbl._refine import reuse
from symsbl._refine.engine import Engine, Settings
from symsbl._refine.sensitivity import Passes

pytestmark = pytest.mark.skipif(jit_module.compiler() is None, reason="no C compiler: nothing is compiled to share")


def _record(seed: int, seconds: float = 2.0):
    """A hardening Duffing oscillator (k 900, c 3, k3 2e7) under a 1-25 Hz multisine, 1 % noise, 500 Hz."""
    system = symsbl.systems.duffing(m=1.0, c=3.0, k=900.0, k3=2e7)
    force = Multisine(rms=20.0, f_min=1.0, f_max=25.0, seed=seed)
    return simulate(system, time_grid(seconds, 500), inputs=force).with_noise(0.01, seed=seed)


def _library():
    x1, x2, F = symsbl.symbols("x1 x2 F")
    return symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])


def _blocks(passes: Passes, theta, guess, w, starts, **options):
    return passes.sensitivities(theta, guess[starts], passes.segments(starts), w, **options)


def test_a_sub_structure_runs_on_its_hosts_compiled_passes_with_its_own_blocks():
    """Inside one scope, the equation error's structure, fitted on another record after an engine of it with three
    candidates was compiled, runs on that engine's compiled functions; its Gauss-Newton blocks, end sensitivities,
    residuals and simulated states are those of passes built for it alone on CasADi's virtual machine (an
    independent evaluation of the same discrete map) to round-off, with white or autoregressive noise and over a
    window of the record."""
    first, second = _record(1), _record(2)
    start = identify(first, _library(), refine=False)
    x1, x2 = start.states
    candidates = {"x2": [(ca.sin(x1), 0.0), (x1**2 * x2, 0.0), (x2**2, 0.0)]}
    settings = Settings(substeps=2, jit=True)
    with reuse.shared_passes():
        host = Engine(start, [first], ("x1", "x2"), settings, candidates)
        assert host.passes.compiled and host.passes._embed is None
        engine = Engine(start, [second], ("x1", "x2"), settings, {})
    passes = engine.passes
    assert passes._embed is not None and passes.kernels is host.passes.kernels
    assert host.names[int(passes._embed[0])] == engine.names[0]  # the embedding goes by (state, term)
    alone = Passes(passes.param, passes.records, jit=False)
    theta = engine.param.theta0 * (1 + 0.02 * np.cos(np.arange(engine.param.n_free)))
    w = np.array([1e4, 1e2])
    starts = passes.segment_starts(200)
    ar = np.array([[0.4, -0.1], [0.2, 0.05]])  # an autoregressive noise model whitens J's rows too
    for options in ({}, {"ar": ar}, {"rows": (int(starts[1]), int(starts[3]))}):
        mine = _blocks(passes, theta, engine.guess, w, starts, **options)
        reference = _blocks(alone, theta, engine.guess, w, starts, **options)
        assert mine.H.shape == reference.H.shape == (len(starts), engine.param.n_free + 2, engine.param.n_free + 2)
        for a, b in ((mine.H, reference.H), (mine.g, reference.g), (mine.end_S, reference.end_S)):
            assert np.allclose(a, b, rtol=1e-9, atol=1e-12 * np.max(np.abs(b)))
        assert np.allclose(mine.rr, reference.rr, rtol=1e-10) and np.array_equal(mine.n_kept, reference.n_kept)
    X = passes.simulate(theta, engine.guess[starts], passes.segments(starts))
    assert np.allclose(X, alone.simulate(theta, engine.guess[starts], alone.segments(starts)), rtol=1e-10, atol=1e-14)


def test_only_a_structure_the_host_computes_and_within_the_share_is_hosted(monkeypatch):
    """A structure with a term the host lacks, other RK4 steps, or too few sensitivities for the host's cost gets
    passes of its own, and so does one whose host holds a term unbounded in value or slope; outside a scope nothing
    is shared."""
    record = _record(3)
    start = identify(record, _library(), refine=False)
    x1, x2 = start.states
    compiled = Settings(substeps=2, jit=True)
    with reuse.shared_passes():  # a host's term outside the structure runs at zero: 0 * inf (its slope at 0) is NaN
        Engine(start, [record], ("x1", "x2"), compiled, {"x2": [(ca.sqrt(ca.fabs(x1)), 0.0)]})
        assert Engine(start, [record], ("x1", "x2"), compiled, {}).passes._embed is None
    with reuse.shared_passes():
        host = Engine(start, [record], ("x1", "x2"), compiled, {"x2": [(ca.sin(x1), 0.0)]})
        assert Engine(start, [record], ("x1", "x2"), compiled, {}).passes.kernels is host.passes.kernels
        other = Engine(start, [record], ("x1", "x2"), compiled, {"x2": [(ca.cos(x1), 0.0)]})
        assert other.passes._embed is None  # cos(x1): not in the host
        steps = Engine(start, [record], ("x1", "x2"), Settings(substeps=3, jit=True), {})
        assert steps.passes._embed is None
        monkeypatch.setattr(reuse, "HOST_SHARE", 1.0)
        assert Engine(start, [record], ("x1", "x2"), compiled, {}).passes._embed is None
    assert Engine(start, [record], ("x1", "x2"), compiled, {}).passes._embed is None


def test_a_refinement_sharing_compiled_passes_returns_the_model_it_returns_alone(monkeypatch):
    """The whole refinement with its term selection and model path, compiled, gives the same model with and without
    sharing (coefficients to 1e-7 of their standard deviations, the same evidence), with fewer compilations."""
    record = _record(4, seconds=4.0)
    library = _library()
    start = identify(record, library, refine=False)
    calls: list = []
    original = jit_module._compile

    def counted(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(jit_module, "_compile", counted)
    monkeypatch.setenv(jit_module.CACHE_ENV, "off")
    monkeypatch.setattr(reuse, "HOST_SHARE", 0.0)
    shared = refine(start, record, library=library, jit=True)
    n_shared = len(calls)
    monkeypatch.setattr(reuse, "HOST_SHARE", np.inf)
    jit_module._MEMORY.clear()
    calls.clear()
    alone = refine(start, record, library=library, jit=True)
    assert n_shared < len(calls)
    assert [eq.names for eq in shared.equations] == [eq.names for eq in alone.equations]
    for a, b in zip(shared.equations, alone.equations):
        for s, t in zip(a.terms, b.terms):
            assert abs(s.coef - t.coef) <= 1e-7 * max(t.std or 0.0, 1e-12 * abs(t.coef)), (s.name, s.coef, t.coef)
    assert shared.metadata["refine"]["log_evidence"] == pytest.approx(
        alone.metadata["refine"]["log_evidence"], abs=1e-6
    )
