"""Compiled functions: kept on disk between runs, loaded only when safe, and equal to the virtual machine's."""

import os
import stat
import subprocess
import sys
import warnings
from collections import OrderedDict

import casadi as ca
import numpy as np
import pytest
from helpers import exactly
from scipy import special

import symsbl
import symsbl._base.jit as jit_module
from symsbl import SimulationError

pytestmark = pytest.mark.skipif(jit_module.compiler() is None, reason="no C compiler")


def mapped(power: int) -> ca.Function:
    """x |-> x^power sin(p) over 16 samples, a distinct structure for each power."""
    x, p = ca.SX.sym("x"), ca.SX.sym("p")
    return ca.Function("f", [x, p], [x**power * ca.sin(p)], ["x", "p"], ["y"]).map(16)


def evaluate(fn: ca.Function) -> np.ndarray:
    return np.asarray(fn(np.linspace(-1.0, 2.0, 16)[None, :], np.full((1, 16), 0.7))).ravel()


@pytest.fixture
def fresh(monkeypatch, tmp_path):
    """A private cache directory, and nothing compiled yet in this process."""
    directory = tmp_path / "jit"
    monkeypatch.setenv(jit_module.CACHE_ENV, str(directory))
    monkeypatch.setattr(jit_module, "_MEMORY", OrderedDict())
    monkeypatch.setattr(jit_module, "_SEEN", {})
    monkeypatch.setattr(jit_module, "_UNUSABLE", set())
    monkeypatch.setattr(jit_module, "_WARNED", set())
    return directory


def forget(monkeypatch):
    """As a new process: nothing in memory, and no compiler that would run."""
    monkeypatch.setattr(jit_module, "_MEMORY", OrderedDict())
    monkeypatch.setattr(jit_module, "_SEEN", {})
    monkeypatch.setattr(jit_module, "_UNUSABLE", set())
    monkeypatch.setattr(jit_module, "_WARNED", set())

    def no_compiler(*args, **kwargs):
        raise AssertionError(f"the compiler ran: {args[0]}")

    monkeypatch.setattr(jit_module.subprocess, "run", no_compiler)


def test_a_compiled_function_is_loaded_from_disk_in_a_later_run_without_compiling(fresh, monkeypatch):
    fn = mapped(3)
    reference = evaluate(fn)  # the virtual machine
    np.testing.assert_allclose(reference, np.linspace(-1.0, 2.0, 16) ** 3 * np.sin(0.7), rtol=1e-14)
    compiled, is_compiled = jit_module.jit_wrap(fn, "f_chunk", True, SimulationError)
    assert is_compiled and [p.suffix for p in fresh.iterdir()] == [".so"]  # no source or partial file left
    np.testing.assert_allclose(evaluate(compiled), reference, rtol=1e-14)
    assert stat.S_IMODE(fresh.stat().st_mode) == 0o700
    forget(monkeypatch)
    again, is_compiled = jit_module.jit_wrap(mapped(3), "f_chunk", True, SimulationError)
    assert is_compiled and again is not compiled
    np.testing.assert_allclose(evaluate(again), reference, rtol=1e-14)
    # jit="auto" on a short record compiles nothing on a first request, but takes what an earlier run compiled
    _, is_compiled = jit_module.jit_wrap(
        mapped(3), "f_chunk", "auto", SimulationError, only_cached=True, key="another key"
    )
    assert is_compiled


def test_a_short_first_request_compiles_nothing_and_the_second_compiles(fresh):
    fn, is_compiled = jit_module.jit_wrap(mapped(2), "f_chunk", "auto", SimulationError, only_cached=True)
    assert not is_compiled and fn is not None and not list(fresh.iterdir())
    fn, is_compiled = jit_module.jit_wrap(mapped(2), "f_chunk", "auto", SimulationError, only_cached=True)
    assert is_compiled and len(list(fresh.iterdir())) == 1


def test_short_requests_compile_once_their_work_together_repays_it(fresh):
    for n, compiled in enumerate((False, False, True)):  # 40 + 40 + 40 units of work against 100
        fn, is_compiled = jit_module.jit_wrap(
            mapped(5), "f_chunk", "auto", SimulationError, only_cached=True, work=40, worth=100
        )
        assert is_compiled is compiled and len(list(fresh.iterdir())) == int(compiled), n
        np.testing.assert_allclose(evaluate(fn), np.linspace(-1.0, 2.0, 16) ** 5 * np.sin(0.7), rtol=1e-14)


def test_a_damaged_library_is_built_again(fresh, monkeypatch):
    # compiled by another process (a library this process has loaded is never read again from its path)
    script = (
        f"import sys; sys.path.insert(0, {os.path.dirname(__file__)!r}); import test_jit, symsbl._base.jit as j, "
        "symsbl; j.jit_wrap(test_jit.mapped(4), 'f_chunk', True, symsbl.SimulationError)"
    )
    subprocess.run([sys.executable, "-c", script], check=True, env=dict(os.environ))
    (library,) = fresh.iterdir()
    damaged = fresh / "damaged"
    damaged.write_bytes(b"not a shared library")
    os.replace(damaged, library)
    fn, is_compiled = jit_module.jit_wrap(mapped(4), "f_chunk", True, SimulationError)
    assert is_compiled and library.read_bytes()[:4] == b"\x7fELF"
    np.testing.assert_allclose(evaluate(fn), evaluate(mapped(4)), rtol=1e-14)


def test_the_least_recently_used_libraries_are_removed_beyond_the_limit(fresh, monkeypatch):
    monkeypatch.setattr(jit_module, "DISK_FILES", 2)
    for power in (5, 6, 7):
        jit_module.jit_wrap(mapped(power), "f_chunk", True, SimulationError)
        os.utime(max(fresh.iterdir(), key=os.path.getmtime), (1e9 + power, 1e9 + power))  # distinct ages
    assert len(list(fresh.iterdir())) == 2
    forget(monkeypatch)
    with pytest.raises(AssertionError, match="the compiler ran"):  # the oldest (power 5) is gone
        jit_module.jit_wrap(mapped(5), "f_chunk", True, SimulationError)
    for power in (6, 7):
        assert jit_module.jit_wrap(mapped(power), "f_chunk", True, SimulationError)[1]


@pytest.mark.parametrize("setting", ["off", "0", ""])
def test_the_disk_cache_can_be_turned_off(setting, monkeypatch, tmp_path):
    monkeypatch.setenv(jit_module.CACHE_ENV, setting)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(jit_module, "_MEMORY", OrderedDict())
    assert jit_module.cache_dir() is None
    fn, is_compiled = jit_module.jit_wrap(mapped(8), "f_chunk", True, SimulationError)
    assert is_compiled and not list(tmp_path.iterdir())
    np.testing.assert_allclose(evaluate(fn), evaluate(mapped(8)), rtol=1e-14)


def test_a_directory_others_may_write_to_is_not_used(monkeypatch, tmp_path):
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    monkeypatch.setenv(jit_module.CACHE_ENV, str(shared))
    assert jit_module.cache_dir() is None
    shared.chmod(0o700)
    assert jit_module.cache_dir() == str(shared)


def test_the_default_directory_follows_xdg_cache_home(monkeypatch, tmp_path):
    monkeypatch.delenv(jit_module.CACHE_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert jit_module.cache_dir() == str(tmp_path / "symsbl" / "jit")


def test_a_library_from_another_compiler_is_not_loaded(fresh, monkeypatch, tmp_path):
    jit_module.jit_wrap(mapped(9), "f_chunk", True, SimulationError)
    monkeypatch.setattr(jit_module, "_MEMORY", OrderedDict())
    other = tmp_path / "cc"
    other.write_text(f'#!/bin/sh\nexec {jit_module.compiler()} "$@"\n')
    other.chmod(0o755)
    monkeypatch.setattr(jit_module, "compiler", lambda: str(other))
    jit_module.jit_wrap(mapped(9), "f_chunk", True, SimulationError)
    assert len(list(fresh.iterdir())) == 2
    assert subprocess.run([str(other), "--version"], capture_output=True).returncode == 0


LACKS_ERFINV = (
    "compiled code: the C library lacks 'erfinv', which the generated C code calls; such functions run on CasADi's "
    "virtual machine instead (the same values, slower)"
)


def with_erfinv() -> ca.Function:
    """x |-> erfinv(tanh(x)) over 16 samples: CasADi generates a call of erfinv, which no C library defines."""
    x = ca.SX.sym("x")
    return ca.Function("g", [x], [ca.erfinv(ca.tanh(x))], ["x"], ["y"]).map(16)


def test_code_calling_a_function_the_c_library_lacks_runs_on_the_virtual_machine_after_one_warning(fresh, monkeypatch):
    fn = with_erfinv()
    z = np.linspace(-1.0, 2.0, 16)[None, :]
    reference = np.asarray(fn(z)).ravel()  # the virtual machine
    np.testing.assert_allclose(reference, special.erfinv(np.tanh(z.ravel())), rtol=1e-6)  # CasADi: to 5e-7
    with pytest.warns(RuntimeWarning, match=exactly(LACKS_ERFINV)):
        wrapped, is_compiled = jit_module.jit_wrap(fn, "g_chunk", "auto", SimulationError)
    assert wrapped is fn and not is_compiled
    np.testing.assert_array_equal(np.asarray(wrapped(z)).ravel(), reference)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same function again: no second warning, nothing compiled
        monkeypatch.setattr(jit_module.subprocess, "run", lambda *a, **k: pytest.fail("the compiler ran"))
        assert jit_module.jit_wrap(fn, "g_chunk", "auto", SimulationError) == (fn, False)
    with pytest.raises(
        SimulationError,
        match=exactly(
            "jit: expected generated C code that runs for jit=True, received the C library lacks 'erfinv', which the "
            "generated C code calls; pass jit='auto'"
        ),
    ):
        jit_module.jit_wrap(fn, "g_chunk", True, SimulationError)
    forget(monkeypatch)  # a later run finds the library on disk, does not compile it again, and warns again
    with pytest.warns(RuntimeWarning, match=exactly(LACKS_ERFINV)):
        assert jit_module.jit_wrap(with_erfinv(), "g_chunk", "auto", SimulationError)[1] is False
    assert [p.suffix for p in fresh.iterdir()] == [".so"]


class _Twice(ca.Callback):
    """y = 2 x computed in Python: a Function CasADi cannot export to C."""

    def __init__(self):
        ca.Callback.__init__(self)
        self.construct("twice", {})

    def get_n_in(self):
        return 1

    def get_n_out(self):
        return 1

    def eval(self, arg):
        return [2 * arg[0]]


def test_a_function_casadi_cannot_export_runs_on_the_virtual_machine_after_one_warning(fresh, monkeypatch, capsys):
    twice = _Twice()
    x = ca.MX.sym("x")
    fn = ca.Function("h", [x], [twice(x)], ["x"], ["y"]).map(4)
    monkeypatch.setattr(jit_module.subprocess, "run", lambda *a, **k: pytest.fail("the compiler ran"))
    with pytest.warns(RuntimeWarning) as caught:
        wrapped, is_compiled = jit_module.jit_wrap(fn, "h_chunk", "auto", SimulationError)
    assert [str(w.message) for w in caught] == [
        "compiled code: CasADi cannot generate C code for CallbackInternal; such functions run on CasADi's virtual "
        "machine instead (the same values, slower)"
    ]
    assert wrapped is fn and not is_compiled and capsys.readouterr().err == ""  # CasADi's own notice is not shown
    np.testing.assert_array_equal(np.asarray(wrapped(np.arange(4.0)[None, :])).ravel(), [0.0, 2.0, 4.0, 6.0])


def test_the_command_identifies_with_a_library_term_the_c_library_lacks(tmp_path, duffing_system):
    # the dynamic linker ended the process (exit 127) at the compiled function's first call of erfinv
    record = symsbl.simulate(duffing_system, symsbl.time_grid(0.05, 8192), inputs=symsbl.Sine(100.0, 10.0))
    symsbl.write_trajectory(record.with_noise(0.004, seed=1), tmp_path / "train.csv")
    (tmp_path / "erfinv.py").write_text(
        "import casadi as ca\nimport symsbl\n"
        "x1, x2, F = symsbl.symbols('x1 x2 F')\n"
        "library = symsbl.Library([x2, x1**3, F, ca.erfinv(ca.tanh(x1))], [x1, x2, F])\n"
    )
    argv = ["identify", "train.csv", "--states", "x1,x2", "--inputs", "F", "--library", "erfinv.py", "--quiet"]
    env = {**os.environ, jit_module.CACHE_ENV: str(tmp_path / "jit")}
    done = subprocess.run(
        [sys.executable, "-m", "symsbl", *argv, "--json", "m.json"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert done.stderr.splitlines() == [f"symsbl identify: warning: {LACKS_ERFINV}"]
    assert "erfinv(tanh(x1))" in done.stdout  # the term was kept: the simulations ran it too
    # the model file it wrote reads back: erfinv is in the model file's grammar
    model = symsbl.IdentifiedModel.load(tmp_path / "m.json")
    assert "erfinv(tanh(x1))" in model.equation("x2").names


def test_a_caller_that_calls_a_function_often_may_compile_a_larger_source(fresh):
    """Under jit="auto" a source beyond the bound runs on the virtual machine (one evaluation does not pay for
    gcc), and a caller that will call it thousands of times (a fit's passes) raises the bound."""
    fn = mapped(5)
    reference = evaluate(fn)
    small, is_compiled = jit_module.jit_wrap(fn, "f_chunk", "auto", SimulationError, max_source=100)
    assert not is_compiled and small is fn and not list(fresh.iterdir())
    large, is_compiled = jit_module.jit_wrap(mapped(5), "f_chunk", "auto", SimulationError, max_source=10**6)
    assert is_compiled and len(list(fresh.iterdir())) == 1
    np.testing.assert_allclose(evaluate(large), reference, rtol=1e-14)
    from symsbl._refine.sensitivity import FIT_SOURCE

    assert jit_module.MAX_AUTO_SOURCE < FIT_SOURCE  # the refinement's passes compile what a one-off would not


def test_a_large_source_is_compiled_at_a_lower_optimisation_and_kept_apart(fresh, monkeypatch):
    """Generated C over the large-source bound is compiled with the large flags (gcc's -O3 time grows faster than
    the source), gives the virtual machine's values and is kept under its own name: the same function under a
    higher bound compiles again, at -O3, into a second library."""
    calls = []
    run = subprocess.run

    def spy(args, *a, **k):
        calls.append(list(args))
        return run(args, *a, **k)

    monkeypatch.setattr(jit_module.subprocess, "run", spy)
    monkeypatch.setattr(jit_module, "LARGE_SOURCE", 100)
    reference = evaluate(mapped(6))
    compiled, is_compiled = jit_module.jit_wrap(mapped(6), "f_chunk", True, SimulationError)
    assert is_compiled and calls[-1][1] == "-O1" and len(list(fresh.iterdir())) == 1
    np.testing.assert_allclose(evaluate(compiled), reference, rtol=1e-14)
    forget(monkeypatch)
    monkeypatch.setattr(jit_module.subprocess, "run", spy)
    monkeypatch.setattr(jit_module, "LARGE_SOURCE", 10**9)
    again, is_compiled = jit_module.jit_wrap(mapped(6), "f_chunk", True, SimulationError)
    assert is_compiled and calls[-1][1] == "-O3" and len(list(fresh.iterdir())) == 2
    np.testing.assert_allclose(evaluate(again), reference, rtol=1e-14)
