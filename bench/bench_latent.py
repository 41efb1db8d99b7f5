"""Latent states: Bouc-Wen systems identified from the position alone, and systems with nothing hidden.

Each case: 4 steady-state periods (4.096 s each at 1 kHz) of a 4-100 Hz random-phase multisine, the
position only, white noise of a given share of its standard deviation; ``symsbl.identify`` with the
states (x1, x2, x3), ``x1' = x2`` declared and the Eq. 21 dictionary to degree 3 (76 candidates).
Printed per case: the verdict, whether the law (or the force) found is the true one, the worst
relative error of the scale-free parameters (1/m, k/m, c/m and the law's coefficients with the
latent scale removed), the held-out NRMSE (a fresh multisine at 60 % of the force, steady state,
noise-free truth) and the time.

A transient record (16.4 s from rest under a multisine whose period, 65.5 s, is longer than the
record, so nothing repeats) is also identified for each Bouc-Wen case at 1 % noise.

Run: ``python bench/bench_latent.py [--quick]`` (quick: one seed per case).
"""

import sys
import time

import _report  # bench/ is on sys.path when run as a script
import numpy as np

import symsbl

FS, PERIOD = 1000.0, 4.096
N = int(FS * PERIOD)
#: (name, system parameters, true law {term: (parameter, sign, degree in x3)} or None, true force terms)
CASES = [
    (
        "Bouc-Wen n=1 (A 4e4, a 600, b -300)",
        dict(A=4e4, n=1, a=600.0, b=-300.0, m=1.5, c=6.0, k=3e4),
        {"x2": ("A", 1, 0), "x3*Abs(x2)": ("a", -1, 1), "x2*Abs(x3)": ("b", -1, 1)},
    ),
    (
        "Bouc-Wen n=1 saturating (a = b = 250)",
        dict(A=6e4, n=1, a=250.0, b=250.0, m=2.0, c=10.0, k=3e4),
        {"x2": ("A", 1, 0), "x3*Abs(x2)": ("a", -1, 1), "x2*Abs(x3)": ("b", -1, 1)},
    ),
    (
        "Bouc-Wen n=2 (a 2.8, b 1.2)",
        dict(A=4e4, n=2, a=2.8, b=1.2, m=1.2, c=5.0, k=4e4),
        {"x2": ("A", 1, 0), "x3*Abs(x2)*Abs(x3)": ("a", -1, 2), "x2*x3**2": ("b", -1, 2)},
    ),
    (
        "Bouc-Wen n=2 pinched (a 9, b -5)",
        dict(A=3e4, n=2, a=9.0, b=-5.0, m=1.0, c=8.0, k=2e4),
        {"x2": ("A", 1, 0), "x3*Abs(x2)*Abs(x3)": ("a", -1, 2), "x2*x3**2": ("b", -1, 2)},
    ),
    ("linear (nothing hidden)", dict(m=1.5, c=6.0, k=5e4), None),
    ("Duffing (nothing hidden)", dict(m=1.5, c=30.0, k=5e4, k3=3e9), None),
]


def forcing(rms, seed, periods):
    t = np.arange(periods * N) / FS
    u = symsbl.Multisine(rms=rms, f_min=4.0, f_max=100.0, seed=seed, period=PERIOD)(t)
    return t, symsbl.Sampled(t, u, kind="periodic")


def system_of(params):
    if "A" in params:
        return symsbl.systems.bouc_wen(**params)
    if "k3" in params:
        return symsbl.systems.duffing(**params)
    return symsbl.systems.linear(**params)


def steady(system, rms, seed, periods, warm):
    t, u = forcing(rms, seed, warm + periods)
    return symsbl.simulate(system, t, inputs=u, method="rk4", substeps=8).slice(warm * N)


def errors(model, params, law):
    v = model.equation("x2")
    m = params["m"]
    errs = [v.coef("F") * m - 1, -v.coef("x1") / params["k"] * m - 1, -v.coef("x2") / params["c"] * m - 1]
    if law:
        s = -next(t for t in v.terms if t.name == "x3").coef * m
        for name, (p, sign, degree) in law.items():
            errs.append(model.equation("x3").coef(name) * s ** (1 - degree) / (sign * params[p]) - 1)
    if "k3" in params:
        errs.append(-v.coef("x1**3") * m / params["k3"] - 1)
    return max(abs(e) for e in errs)


def transient(system, seed):
    t = np.arange(4 * N) / FS
    u = symsbl.Multisine(rms=40.0, f_min=4.0, f_max=100.0, seed=seed + 1, period=16 * PERIOD)(t)
    return symsbl.simulate(system, t, inputs=symsbl.Sampled(t, u, kind="cubic"), method="rk4", substeps=8)


def run(name, params, law, noise, seed, periodic=True):
    system = system_of(params)
    clean = steady(system, 40.0, seed + 1, 4, 2) if periodic else transient(system, seed)
    x = clean.column("x1")
    rng = np.random.default_rng(100 + seed)
    record = symsbl.Trajectory(
        clean.t - clean.t[0],
        (x + noise * x.std() * rng.standard_normal(x.size))[:, None],
        clean.inputs,
        ("x1",),
        ("F",),
    )
    x1, x2, x3, F = symsbl.symbols("x1 x2 x3 F")
    start = time.perf_counter()
    model = symsbl.identify(
        record, symsbl.paper([x1, x2, x3], [F], degree=3), states=("x1", "x2", "x3"), kinematics="x1:x2"
    )
    seconds = time.perf_counter() - start
    verdict = model.metadata["latent"]["verdict"]
    if law:
        right = verdict == "hidden" and sorted(model.equation("x3").names) == sorted(law)
    else:
        expected = ["F", "x1", "x2"] + (["x1**3"] if "k3" in params else [])
        right = verdict.startswith("nothing hidden") and model.equation("x2").names == expected
    worst = errors(model, params, law) if right else np.nan
    truth = steady(system, 24.0, 50 + seed, 1, 2).column("x1")
    predicted = steady(model.to_system(), 24.0, 50 + seed, 1, 2).column("x1")
    held = float(np.sqrt(np.mean((predicted - truth) ** 2)) / truth.std())
    print(
        f"| {name}{'' if periodic else ', transient record'} | {100 * noise:g} % | {seed} | {verdict} | "
        f"{'yes' if right else 'NO'} | {100 * worst:.3g} % | {100 * held:.3g} % | {seconds:.1f} s |",
        flush=True,
    )
    return right, worst, held, seconds


def main():
    quick = "--quick" in sys.argv
    print("| case | noise | seed | verdict | right structure | worst parameter error | held-out NRMSE | time |")
    print("|---|---|---|---|---|---|---|---|")
    results = []
    for name, params, law in CASES:
        for noise in (0.01,) if quick else (0.005, 0.01, 0.02):
            for seed in (0,) if quick else (0, 1):
                results.append(run(name, params, law, noise, seed))
        if law:
            results.append(run(name, params, law, 0.01, 0, periodic=False))
    right = sum(r[0] for r in results)
    print(
        f"\nright structure in {right}/{len(results)} runs; worst parameter error "
        f"{100 * np.nanmax([r[1] for r in results]):.3g} %, worst held-out NRMSE "
        f"{100 * max(r[2] for r in results):.3g} %, median time {np.median([r[3] for r in results]):.1f} s"
    )
    _report.write_page("latent", __doc__)


if __name__ == "__main__":
    main()
