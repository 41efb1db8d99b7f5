"""Output-error refinement (:func:`symsbl.refine`): time against record length, against a scipy
baseline on the same problem, and the default identification of a 10^7-sample record.

Data: the Duffing oscillator of :func:`symsbl.systems.duffing` (x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F)
driven by a random-phase multisine (60 N rms, 2-30 Hz, period 1 s), simulated by fixed-step RK4 at
32768 Hz (one step per sample, CasADi-compiled) from rest, with 1 % of each state's standard deviation
added as white noise. Library: ``polynomial([x1, x2], 3) + inputs([F])`` (11 terms).

1. **Refinement time against N** (1 s, 10 s, 100 s of data). The structure is fixed: the starting
   point is ``identify(train, library, refine=False)`` (equation error, weak form), then
   ``refine(start, train, select=False, max_samples=train.n_samples)`` fits every sample as one
   record (no windows). The first call of the session (1 s) includes compiling the sensitivity
   pass; the table gives the best of the warm repeats. For reference, the default
   ``identify(train, library)`` (term selection on the output-error evidence, refinement on at most
   2^18 samples as evenly spaced windows) is timed on the same records.
2. **scipy baseline** on the same problem: ``scipy.optimize.least_squares`` (trf, 2-point forward
   differences with a relative step of 1e-6, ``x_scale="jac"``, tolerances 1e-12 so that only the
   budget stops it) driving ``scipy.integrate.solve_ivp`` single shooting (RK45, rtol 1e-8, atol
   1e-11 times each state's standard deviation). The unknowns are the same as refine's (every
   coefficient of the equation-error structure and the initial state), scaled by the starting
   coefficients and the states' standard deviations, starting from the same point (equation-error
   coefficients, first sample as initial state). The input runs between samples by the same
   not-a-knot cubic spline refine uses, evaluated with Python scalars (as cheap as ``np.interp``).
   The cost is E = 1/2 sum_c w_c ||y_c - x_c||^2 with w_c fixed to the noise precisions of the
   refined model (``1 / equation(c).noise_var``). symsbl's E is that of its refined model
   re-simulated (:func:`symsbl.validate_model`: RK4 as in the fit, initial state fitted on the
   record's first stretch, so an upper bound of its optimum). scipy runs for a wall-clock budget,
   checked inside the simulation too; "reaches" means E <= E_symsbl + 0.5 (within one standard
   deviation along any single direction), and the time it first did so is read from the history of
   its evaluations. When it never does, the speed-up is only bounded below by budget / symsbl time.
3. **A 10^7-sample record** (305 s), simulated in pieces of 2^20 samples (the state carried from
   piece to piece), written once to an uncompressed ``.npz`` (columns t, x1, x2, F), then identified
   with the default settings, ``identify_stream(open_npz(path, ...), library)``, in a fresh
   subprocess (imports and compilation included in its peak memory, compilation in its time): the
   time of the call, the subprocess's peak resident memory (its own ``ru_maxrss`` and the parent's
   ``RUSAGE_CHILDREN``), the support, the largest relative coefficient error against the truth and
   the samples refined on. Target: under 60 s and 2 GiB.

Every timing runs with one BLAS thread (:func:`_report.one_blas_thread`). The machine is shared:
the load average is printed with the results.

Run: ``PYTHONPATH=. python bench/bench_refine.py [--quick] [--budget 120] [--durations 1,10,100]
[--stream-samples 1e7] [--skip 2,3]`` (``--quick``: 1 s only, scipy budget 20 s, 10^6 samples in part 3).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np
from _report import one_blas_thread, table, timed, write_page  # noqa: E402  (bench/ is on sys.path when run as a script)

from symsbl import (
    Multisine,
    Sampled,
    compare_to_truth,
    identify,
    identify_stream,
    inputs,
    open_npz,
    polynomial,
    refine,
    simulate,
    symbols,
    systems,
    time_grid,
    validate_model,
)

FS = 32768
NOISE = 0.01
PIECE = 2**20
X1, X2, F = symbols("x1 x2 F")
LIB = polynomial([X1, X2], 3) + inputs([F])
FORCE = dict(rms=60.0, f_min=2.0, f_max=30.0)
NAMES = dict(states=("x1", "x2"), inputs=("F",))


# ------------------------------------------------------------------------------------------- data


def record(seconds: float, seed: int = 1):
    """``seconds`` of the noisy Duffing at ``FS`` (RK4 from rest, multisine of seed ``seed``)."""
    clean = simulate(systems.duffing(), time_grid(seconds, FS), inputs=Multisine(**FORCE, seed=seed), method="rk4")
    return clean.with_noise(NOISE, seed=seed)


def write_record(directory: Path, n: int, seed: int = 1) -> Path:
    """Simulate ``n`` samples piece by piece into ``.npy`` memmaps, add the noise, zip them into an NPZ.

    The noise level is 1 % of each state's standard deviation over the whole record (a second pass)."""
    cols = {k: np.lib.format.open_memmap(directory / f"{k}.npy", mode="w+", shape=(n,)) for k in ("t", "x1", "x2", "F")}
    system, force = systems.duffing(), Multisine(**FORCE, seed=seed)
    x0, a = np.zeros(2), 0
    while a < n:
        b = min(a + PIECE, n)
        t = np.arange(a, b + 1) / FS  # one extra sample: the next piece starts from its state
        sim = simulate(system, t, inputs=force, x0=x0, method="rk4")
        x0 = sim.states[-1]
        cols["t"][a:b], cols["F"][a:b] = t[:-1], sim.inputs[:-1, 0]
        cols["x1"][a:b], cols["x2"][a:b] = sim.states[:-1, 0], sim.states[:-1, 1]
        a = b
    rng = np.random.default_rng(seed)
    for k in ("x1", "x2"):
        scale = NOISE * float(np.std(cols[k]))
        for a in range(0, n, PIECE):
            b = min(a + PIECE, n)
            cols[k][a:b] += scale * rng.standard_normal(b - a)
    for mm in cols.values():
        mm.flush()
    del cols
    path = directory / "duffing.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for k in ("t", "x1", "x2", "F"):
            zf.write(directory / f"{k}.npy", arcname=f"{k}.npy")
            (directory / f"{k}.npy").unlink()
    return path


# ------------------------------------------------------------------------------------------- cost


def weights(model) -> np.ndarray:
    """The refined model's noise precisions of the states, in state order."""
    return np.array([1.0 / model.equation(s).noise_var for s in model.state_names])


def cost(train, states: np.ndarray, w: np.ndarray) -> float:
    """E = 1/2 sum_c w_c ||y_c - x_c||^2."""
    return 0.5 * float(np.sum(w * (train.states - states) ** 2))


def start_cost(start, train, w) -> float:
    """E of the starting point: the equation-error model simulated from the first sample (RK4, cubic input)."""
    sim = simulate(
        start.to_system(),
        train.t,
        inputs=Sampled(train.t, train.column("F"), kind="cubic"),
        x0=train.states[0],
        method="rk4",
    )
    return cost(train, sim.states, w)


def refined_cost(model, train, w) -> float:
    """E of the refined model, re-simulated as it was fitted, from an initial state fitted to the record."""
    check = validate_model(model, train)
    assert check.status == "ok", check.message
    return cost(train, check.simulated.states, w)


# ------------------------------------------------------------------------------------------ scipy


class Budget(Exception):
    """The baseline's wall-clock budget ran out."""


def scalar_spline(t: np.ndarray, u: np.ndarray):
    """The not-a-knot cubic spline of ``u`` on the uniform grid ``t``, as a scalar Python function."""
    from scipy.interpolate import CubicSpline

    c0, c1, c2, c3 = (row.tolist() for row in CubicSpline(t, u).c)
    t0, h, last = float(t[0]), float(t[1] - t[0]), len(t) - 2

    def spline(tt):
        i = min(max(int((tt - t0) / h), 0), last)
        d = tt - (t0 + i * h)
        return ((c0[i] * d + c1[i]) * d + c2[i]) * d + c3[i]

    return spline


def rhs_function(model):
    """The model's right-hand side as one scalar Python function ``(x..., u..., free coefficients...) -> list``
    (sympy ``lambdify`` to ``math``: as fast as a hand-written right-hand side); fixed equations keep
    their coefficients."""
    import sympy as sp

    args = [sp.Symbol(n) for n in model.state_names + model.input_names]
    free = [eq for eq in model.equations if not eq.fixed]
    coefs = sp.symbols(f"c0:{sum(len(eq.terms) for eq in free)}")
    rhs, k = [], 0
    for eq in model.equations:
        if eq.fixed:
            rhs.append(sum(c * t.sympy for c, t in zip(eq.coefs, eq.terms)))
            continue
        rhs.append(sum(coefs[k + j] * t.sympy for j, t in enumerate(eq.terms)))
        k += len(eq.terms)
    return sp.lambdify(args + list(coefs), rhs, "math")


def scipy_fit(start, train, w: np.ndarray, budget: float) -> dict:
    """least_squares(trf, 2-point) over the coefficients and x0 of a solve_ivp (RK45) single shooting."""
    from scipy.integrate import solve_ivp
    from scipy.optimize import least_squares

    f = rhs_function(start)
    theta0 = np.concatenate([eq.coefs for eq in start.equations if not eq.fixed])
    tscale, xscale = np.abs(theta0), train.states.std(axis=0)
    t, y, sw = train.t, train.states, np.sqrt(w)
    spline = scalar_spline(t, train.column("F"))
    clock0 = time.perf_counter()
    history = []  # (seconds since the start, E) of every simulation

    def rhs_of(theta):
        coefs = theta.tolist()

        def rhs(tt, x):
            if time.perf_counter() - clock0 > budget:  # abort inside a long simulation too
                raise Budget
            return f(*x.tolist(), spline(tt), *coefs)

        return rhs

    def residuals(v):
        x0 = v[theta0.size :] * xscale
        sol = solve_ivp(
            rhs_of(v[: theta0.size] * tscale),
            (t[0], t[-1]),
            x0,
            method="RK45",
            t_eval=t,
            rtol=1e-8,
            atol=1e-11 * xscale,
        )
        r = np.full(y.size, 1e10) if sol.status != 0 else ((y - sol.y.T) * sw).ravel()
        history.append((time.perf_counter() - clock0, 0.5 * float(r @ r)))
        return r

    v0 = np.concatenate([theta0 / tscale, train.states[0] / xscale])
    try:
        res = least_squares(
            residuals,
            v0,
            jac="2-point",
            method="trf",
            x_scale="jac",
            diff_step=1e-6,
            ftol=1e-12,
            xtol=1e-12,
            gtol=1e-12,
        )
        status = f"stopped: {res.message}"
    except Budget:
        status = f"budget of {budget:.0f} s ran out"
    return dict(history=history, seconds=time.perf_counter() - clock0, status=status)


def first_reach(history, threshold: float):
    """Seconds until an evaluation first had E <= threshold (None if never)."""
    return next((s for s, e in history if e <= threshold), None)


# ---------------------------------------------------------------------------------------- parts


def refinement_vs_n(durations):
    """Part 1: refine with the structure fixed on every sample; the default identify for reference."""
    rows, ident_rows, cases = [], [], []
    for seconds in durations:
        train = record(seconds)
        start = identify(train, LIB, refine=False)

        def fit(start=start, train=train):
            return refine(start, train, select=False, max_samples=train.n_samples)

        cold = None
        if not cases:
            _, cold = timed(fit, repeats=1)  # the session's first call: compiles the sensitivity pass
        model, dt = timed(fit, repeats=3 if seconds <= 1 else 2 if seconds <= 10 else 1)
        w = weights(model)
        e0, e1 = start_cost(start, train, w), refined_cost(model, train, w)
        info = model.metadata["refine"]
        cases.append(dict(seconds=seconds, train=train, start=start, model=model, t=dt, cold=cold, w=w, e0=e0, e1=e1))
        growth = "" if len(cases) == 1 else f"{dt / cases[-2]['t']:.1f}x"
        rows.append(
            [
                f"{seconds:g} s",
                train.n_samples,
                f"{dt:.2f}" + ("" if cold is None else f" ({cold:.2f} cold)"),
                f"{1e6 * dt / train.n_samples:.2f}",
                info["passes"],
                len(info["stages"]),
                growth,
                f"{e0:.6g}",
                f"{e1:.6g}",
                f"{compare_to_truth(model, systems.duffing()).max_error():.1e}",
            ]
        )
        reps = 2 if seconds <= 10 else 1
        default, dt_default = timed(lambda train=train: identify(train, LIB), repeats=reps)
        d_info = default.metadata.get("refine", {})
        ident_rows.append(
            [
                f"{seconds:g} s",
                train.n_samples,
                f"{dt_default:.2f}",
                d_info.get("samples", d_info),
                d_info.get("passes", "-"),
                ", ".join(default.equation("x2").names),
                f"{compare_to_truth(default, systems.duffing()).max_error():.1e}",
            ]
        )
    table(
        "Output-error refinement, structure fixed, every sample (refine(start, train, select=False, "
        "max_samples=N); best of warm repeats)",
        [
            "data",
            "N samples",
            "time (s)",
            "s per 10^6 samples",
            "passes",
            "stages",
            "time / previous (per decade)",
            "E start",
            "E refined",
            "max rel. coef. error",
        ],
        rows,
    )
    table(
        "Default identify(train, library): equation error, then refinement with term selection on at most 2^18 samples",
        ["data", "N samples", "time (s)", "samples refined on", "passes", "x2' support", "max rel. coef. error"],
        ident_rows,
    )
    return cases


def against_scipy(cases, budget: float):
    """Part 2: the scipy baseline from the same start, with the refined model's weights."""
    rows = []
    for case in cases:
        out = scipy_fit(case["start"], case["train"], case["w"], budget)
        hist = out["history"]
        best = min((e for _, e in hist), default=math.nan)
        reach = first_reach(hist, case["e1"] + 0.5)
        first_sim = f"{hist[0][0]:.2f}" if hist else f"> {out['seconds']:.0f} (none finished)"
        if reach is not None:
            ratio, reached = f"{reach / case['t']:.0f}x", f"yes, after {reach:.1f} s"
        else:
            ratio, reached = f">= {out['seconds'] / case['t']:.0f}x (lower bound)", "no"
        if case["cold"] is not None:
            bound = "" if reach is not None else ">= "
            ratio += f" ({bound}{(reach or out['seconds']) / case['cold']:.0f}x against the cold call)"
        symsbl_t = f"{case['t']:.2f}" + ("" if case["cold"] is None else f" ({case['cold']:.2f} cold)")
        rows.append(
            [
                f"{case['seconds']:g} s",
                symsbl_t,
                f"{case['e1']:.8g}",
                f"{out['seconds']:.1f}",
                len(hist),
                first_sim,
                out["status"],
                f"{best:.8g}",
                reached,
                ratio,
            ]
        )
    table(
        f"Same problem, same start, same weights: symsbl.refine against scipy least_squares(trf, 2-point) + "
        f"solve_ivp(RK45, rtol 1e-8) single shooting (budget {budget:.0f} s per case)",
        [
            "data",
            "symsbl (s)",
            "symsbl E",
            "scipy wall time (s)",
            "scipy simulations",
            "scipy first simulation (s)",
            "scipy status",
            "scipy best E",
            "scipy reaches symsbl's E + 0.5",
            "speed-up (scipy time to reach / symsbl)",
        ],
        rows,
    )


def stream_child(path: str) -> None:
    """Run in a subprocess: identify the NPZ record with the default settings; print one JSON line."""
    with one_blas_thread():
        model, dt = timed(lambda: identify_stream(open_npz(path, **NAMES), LIB), repeats=1)
    truth = compare_to_truth(model, systems.duffing())
    info = model.metadata.get("refine", {})
    print(
        json.dumps(
            dict(
                seconds=dt,
                maxrss_kib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
                support={eq.lhs: eq.names for eq in model.equations},
                max_error=truth.max_error(),
                exact=bool(truth.exact_support),
                samples=info.get("samples", info),
                passes=info.get("passes"),
                model=str(model),
            )
        )
    )


def long_record(n: int):
    """Part 3: write an ``n``-sample record, identify it in a subprocess; time, peak memory, accuracy."""
    with tempfile.TemporaryDirectory(prefix="symsbl_bench_refine_") as tmp:
        t0 = time.perf_counter()
        path = write_record(Path(tmp), n)
        print(
            f"\nsimulated and wrote {n:.0e} samples ({n / FS:.0f} s at {FS} Hz, "
            f"{path.stat().st_size / 2**20:.0f} MiB) in {time.perf_counter() - t0:.1f} s (not timed below)"
        )
        root = str(Path(__file__).resolve().parent.parent)  # symsbl importable in the subprocess as here
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])))
        done = subprocess.run(
            [sys.executable, __file__, "--stream-child", str(path)],
            check=False,
            capture_output=True,
            text=True,
            env=env,
        )
    if done.returncode != 0:
        print(f"\nthe identification subprocess failed (exit {done.returncode}):\n{done.stderr[-4000:]}")
        return
    out = json.loads(done.stdout.strip().splitlines()[-1])
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 2**20
    support = "; ".join(f"{k}' = {' + '.join(v)}" for k, v in out["support"].items())
    table(
        f"Default identify_stream on a {n:.0e}-sample memory-mapped NPZ record (fresh subprocess)",
        [
            "N samples",
            "time (s)",
            "peak RSS, subprocess (GiB)",
            "RUSAGE_CHILDREN (GiB)",
            "support",
            "exact support",
            "max rel. coef. error",
            "refined on",
            "passes",
        ],
        [
            [
                n,
                f"{out['seconds']:.1f}",
                f"{out['maxrss_kib'] / 2**20:.2f}",
                f"{children:.2f}",
                support,
                out["exact"],
                f"{out['max_error']:.1e}",
                out["samples"],
                out["passes"],
            ]
        ],
    )
    print(f"\nmodel:\n{out['model']}")
    if done.stderr.strip():
        print(f"\nsubprocess stderr (last lines):\n{done.stderr.strip()[-1500:]}")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="1 s only, scipy budget 20 s, 10^6 samples in part 3")
    parser.add_argument("--budget", type=float, default=None, help="scipy's wall-clock budget per case (s; 120)")
    parser.add_argument("--stream-samples", type=float, default=None, help="samples of part 3's record (1e7)")
    parser.add_argument("--durations", default=None, help="record lengths of parts 1-2 in seconds (1,10,100)")
    parser.add_argument("--skip", default="", help="parts to skip, e.g. '3' or '2,3'")
    parser.add_argument("--stream-child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.stream_child:
        stream_child(args.stream_child)
        return
    budget = args.budget if args.budget is not None else 20.0 if args.quick else 120.0
    n_stream = int(args.stream_samples if args.stream_samples is not None else 1e6 if args.quick else 1e7)
    durations = (1.0,) if args.quick else (1.0, 10.0, 100.0)
    if args.durations:
        durations = tuple(float(d) for d in args.durations.split(","))
    skip = set(args.skip.replace(" ", "").split(","))
    print(f"load average at start: {', '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)")
    t0 = time.perf_counter()
    with one_blas_thread():
        cases = refinement_vs_n(durations)
        if "2" not in skip:
            against_scipy(cases, budget)
    del cases
    if "3" not in skip:
        long_record(n_stream)
    print(
        f"\nload average at the end: {', '.join(f'{x:.2f}' for x in os.getloadavg())}; "
        f"total {time.perf_counter() - t0:.0f} s; "
        f"this process's peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB"
    )
    write_page("refine", __doc__)


if __name__ == "__main__":
    main()
