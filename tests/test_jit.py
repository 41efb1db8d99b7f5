"""Compiled functions: kept on disk between runs, loaded only when safe, and equal to the virtual machine's."""

import os
import stat
import subprocess
import sys
from collections import OrderedDict

import casadi as ca
import numpy as np
import pytest

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
    monkeypatch.setattr(jit_module, "_SEEN", set())
    return directory


def forget(monkeypatch):
    """As a new process: nothing in memory, and no compiler that would run."""
    monkeypatch.setattr(jit_module, "_MEMORY", OrderedDict())
    monkeypatch.setattr(jit_module, "_SEEN", set())

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
