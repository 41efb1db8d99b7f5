"""Simulation speed and accuracy: symsbl (CasADi cvodes, RK4 mapaccum VM/JIT) against scipy.integrate.solve_ivp.

Duffing (m=1, c=20, k=1e4, k3=1e9) and Coulomb friction (kc=1) driven by 100 N at 10 Hz from rest, output on
every sample at 32768 Hz. Errors are max |x1 - x1_ref| / max |x1_ref| against a tight reference (Duffing:
DOP853 at rtol 1e-12, atol 1e-15; Coulomb: RK4 with 64 substeps per sample). scipy's adaptive solvers stall on
the Coulomb discontinuity, so each of their runs has a deadline. Times are medians of 3 runs after a warm-up
(single runs for the 10 s Duffing record).

Run: ``PYTHONPATH=. python bench/bench_simulate.py``
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np
from scipy.integrate import solve_ivp

from symsbl import Sine, simulate, systems, time_grid

sys.path.insert(0, os.path.dirname(__file__))
import _report  # noqa: E402  (bench/ is on sys.path when run as a script)

FS = 32768
DEADLINE = 10.0  # seconds allowed to each scipy run on the Coulomb system
M, C, K, K3, KC, F0, W = 1.0, 20.0, 1e4, 1e9, 1.0, 100.0, 2 * np.pi * 10.0


class DeadlineExceeded(Exception):
    pass


def duffing_rhs(t, x):
    return [x[1], (F0 * np.sin(W * t) - C * x[1] - K * x[0] - K3 * x[0] ** 3) / M]


def coulomb_rhs_with_deadline(deadline, progress):
    def rhs(t, x):
        if time.perf_counter() > deadline:
            raise DeadlineExceeded
        progress[0] = max(progress[0], t)
        return [x[1], (F0 * np.sin(W * t) - C * x[1] - K * x[0] - KC * np.sign(x[1])) / M]

    return rhs


def timed(fn, repeats):
    """The last result and median wall time of ``fn`` (the shared timer)."""
    return _report.timed(fn, repeats, statistic="median")


def rel_err(x1, ref):
    return np.max(np.abs(x1 - ref)) / np.max(np.abs(ref))


def scipy_run(rhs, t, method, rtol, atol):
    sol = solve_ivp(rhs, (t[0], t[-1]), [0.0, 0.0], method=method, t_eval=t, rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError(sol.message)
    return sol.y[0]


def print_table(title, rows, base_label):
    base = dict((r[0], r[1]) for r in rows)[base_label]
    _report.table(
        title,
        ["method", "time", "ratio", "rel. error (x1)"],
        [
            [label, "-", "-", sec]
            if isinstance(sec, str)
            else [label, f"{sec * 1e3:.1f} ms", f"{sec / base:.2f}x", f"{err:.1e}"]
            for label, sec, err in rows
        ],
    )
    print(f"ratio = time / time of '{base_label}'")


def bench_duffing(duration, repeats):
    t = time_grid(duration, FS)
    s = systems.duffing()
    sig = Sine(F0, 10.0)
    ref = scipy_run(duffing_rhs, t, "DOP853", 1e-12, 1e-15)
    rk4_check = simulate(s, t, inputs=sig, method="rk4", substeps=4, jit=True).states[:, 0]
    rows = []

    def add(label, fn, n=repeats):
        x1, sec = timed(fn, n)
        rows.append((label, sec, rel_err(x1, ref)))

    for rtol, atol in ((1e-8, 1e-10), (1e-10, 1e-12)):
        add(
            f"symsbl cvodes BDF, rtol {rtol:g}",
            lambda rtol=rtol, atol=atol: simulate(s, t, inputs=sig, method="cvodes", rtol=rtol, atol=atol).states[:, 0],
        )
    simulate(s, t, inputs=sig, method="rk4", jit=True)  # compile outside the timing (reported below)
    simulate(s, t, inputs=sig, method="rk4", substeps=2, jit=True)
    add("symsbl RK4 mapaccum+JIT, 1 substep", lambda: simulate(s, t, inputs=sig, method="rk4", jit=True).states[:, 0])
    add(
        "symsbl RK4 mapaccum+JIT, 2 substeps",
        lambda: simulate(s, t, inputs=sig, method="rk4", substeps=2, jit=True).states[:, 0],
    )
    add(
        "symsbl RK4 mapaccum, SX virtual machine",
        lambda: simulate(s, t, inputs=sig, method="rk4", jit=False).states[:, 0],
    )
    for rtol, atol in ((1e-8, 1e-10), (1e-10, 1e-12)):
        for method in ("RK45", "DOP853", "LSODA"):
            add(
                f"scipy {method}, rtol {rtol:g}",
                lambda method=method, rtol=rtol, atol=atol: scipy_run(duffing_rhs, t, method, rtol, atol),
                n=repeats if duration <= 1 else 1,
            )
    print_table(
        f"Duffing, {duration:g} s at {FS} Hz ({t.size} samples); reference DOP853 rtol 1e-12 "
        f"(RK4 with 4 substeps agrees with it to {rel_err(rk4_check, ref):.1e})",
        rows,
        "symsbl cvodes BDF, rtol 1e-10",
    )
    return rows


def bench_coulomb():
    t = time_grid(1.0, FS)
    s = systems.coulomb()
    sig = Sine(F0, 10.0)
    ref = simulate(s, t, inputs=sig, method="rk4", substeps=64, jit=True).states[:, 0]
    rows = []
    for sub in (1, 2, 8):
        simulate(s, t, inputs=sig, method="rk4", substeps=sub, jit=True)
        x1, sec = timed(
            lambda sub=sub: simulate(s, t, inputs=sig, method="rk4", substeps=sub, jit=True).states[:, 0], 3
        )
        rows.append((f"symsbl RK4 mapaccum+JIT, {sub} substep(s)", sec, rel_err(x1, ref)))
    x1, sec = timed(lambda: simulate(s, t, inputs=sig, method="rk4", jit=False).states[:, 0], 3)
    rows.append(("symsbl RK4 mapaccum, SX virtual machine", sec, rel_err(x1, ref)))
    t0 = time.perf_counter()
    try:
        simulate(s, t, inputs=sig, method="cvodes")
        rows.append(("symsbl cvodes", time.perf_counter() - t0, np.nan))
    except Exception as err:  # noqa: BLE001 - reported, not handled
        rows.append(("symsbl cvodes", f"fails {time.perf_counter() - t0:.2f} s", None))
        print(f"  cvodes: {str(err)[:110]}...")
    for method in ("RK45", "DOP853", "LSODA"):
        progress = [0.0]
        t0 = time.perf_counter()
        rhs = coulomb_rhs_with_deadline(t0 + DEADLINE, progress)
        try:
            x1 = scipy_run(rhs, t, method, 1e-8, 1e-10)
            rows.append((f"scipy {method}, rtol 1e-8", time.perf_counter() - t0, rel_err(x1, ref)))
        except DeadlineExceeded:
            rows.append((f"scipy {method}, rtol 1e-8", f"DNF in {DEADLINE:g} s", None))
            print(f"  scipy {method}: did not finish in {DEADLINE:g} s (reached t = {progress[0]:.2e} s of 1 s)")
        except Exception as err:  # noqa: BLE001 - reported, not handled
            rows.append((f"scipy {method}, rtol 1e-8", "aborts", None))
            print(
                f"  scipy {method}: aborted after {time.perf_counter() - t0:.2f} s at t = {progress[0]:.2e} s: "
                f"{str(err)[:90]}"
            )
    print_table(
        f"Coulomb (kc = 1), 1 s at {FS} Hz; reference RK4 with 64 substeps",
        rows,
        "symsbl RK4 mapaccum+JIT, 1 substep(s)",
    )


def main():
    s, t = systems.duffing(), time_grid(1.0, FS)
    t0 = time.perf_counter()
    simulate(s, t, inputs=Sine(), method="rk4", substeps=3, jit=True)
    print(
        f"JIT compile + first run of an RK4 chunk (4096 samples): {time.perf_counter() - t0:.2f} s (once per "
        "system, substeps and chunk; cached afterwards)"
    )
    _, sec = timed(lambda: simulate(s, t, inputs=Sine()), 3)
    print(f"simulate(duffing(), 1 s at 32768 Hz, Sine()) with the default method: {sec * 1e3:.1f} ms")
    bench_duffing(1.0, 3)
    bench_duffing(10.0, 1)
    bench_coulomb()
    _report.write_page("simulate", __doc__)


if __name__ == "__main__":
    main()
