"""The weak form's windows: apart (default) or overlapping with whitened rows, against the Cramér-Rao bound.

For each case and noise seed, the equation-error model (``identify(..., refine=False)``) is fitted with
``WeakForm(overlap=q)`` for each ``q`` (1: windows apart; 2: half overlap; 3: a third), and the output-error
model (the default ``identify``) gives the reference: its Laplace posterior standard deviation is the
Cramér-Rao bound of the record (within 1 % in ``tests/test_refine.py``). Columns:

- exact: seeds with the exact support;
- err/CRB: root mean square over seeds and true terms of (error / CRB std), on exact-support fits: how
  many bound standard deviations the estimator is off (1 is efficient);
- z std: standard deviation over seeds and terms of (error / the model's own posterior std): 1 when the
  reported uncertainty is right, above 1 when it is too small (the rows' noise is not what the
  likelihood assumes);
- rows: regression rows.

Cases (none the paper's): m = 2, k = 8e3 with linear damping 6, quadratic drag 5 v|v| + damping 2, or a
cubic spring 3e7; 4096 Hz, 3 s, 1 % noise; a 12 Hz sine or a 2-30 Hz multisine; Eq. 21 dictionary of
degree 3.

``--part paper`` asks which overlap makes the better default beyond these three oscillators: the paper's five
systems (their parameters and dictionaries, Eq. 21 of degree 6, 4 for Bouc-Wen; 32768 Hz, 2 s, 0.4 % noise, the
paper's 10 Hz sine and a 2-30 Hz multisine, ``--seeds`` seeds) and a Duffing sampled at 400 Hz (m = 0.5, c = 3,
k = 2e3, k3 = 2e7, multisine 1-30 Hz, 10 s, 1 % noise, degree 3): per overlap, the fits with the exact support,
the median of the largest coefficient error on those, and the spurious terms met.

Run: ``PYTHONPATH=. python bench/bench_weakform.py [--part oscillators|paper] [--seeds 10] [--overlaps 1,2,3]``.
"""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np
from _report import one_blas_thread, table, write_page  # noqa: E402  (bench/ is on sys.path when run as a script)

from symsbl import Multisine, OdeSystem, Sine, WeakForm, compare_to_truth, identify, paper, simulate, symbols, time_grid
from symsbl._demo import CASES

FS, DURATION, NOISE = 4096, 3.0, 0.01
HEADER = ["system", "forcing", "overlap", "exact", "err/CRB", "z std", "rows"]


def _system(kind):
    x1, x2, F = symbols("x1 x2 F")
    m, k = 2.0, 8e3
    force = {
        "linear": 6.0 * x2 + k * x1,
        "drag": 2.0 * x2 + 5.0 * x2 * abs(x2) + k * x1,
        "cubic": 6.0 * x2 + k * x1 + 3e7 * x1**3,
    }[kind]
    return OdeSystem((x1, x2), (F,), (x2, (F - force) / m), name=kind)


def _forcing(kind, seed):
    if kind == "sine":
        return Sine(60.0, 12.0)
    return Multisine(40.0, 2.0, 30.0, seed=100 + seed)


def _terms(model, system):
    """Per true term of the velocity equation: (estimate, own std), or None when the support is not exact."""
    truth = compare_to_truth(model, system)
    if not truth.exact_support:
        return None
    eq = model.equations[1]
    return {t.name: (t.coef, t.std) for t in eq.terms}


def _true(system):
    import sympy as sp

    rhs = sp.expand(system.to_sympy()[1].rhs)
    return {str(term): float(coef) for coef, term in (p.as_coeff_Mul() for p in sp.Add.make_args(rhs))}


def run(seeds, overlaps):
    library = paper(symbols("x1 x2"), symbols("F"), degree=3)
    rows = []
    for kind in ("linear", "drag", "cubic"):
        system = _system(kind)
        truth = _true(system)
        for forcing in ("sine", "multisine"):
            fits = {q: [] for q in overlaps}
            oe, n_rows = [], {}
            for seed in range(seeds):
                clean = simulate(system, time_grid(DURATION, FS), inputs=_forcing(forcing, seed))
                data = clean.with_noise(NOISE, seed=seed)
                oe.append(_terms(identify(data, library), system))
                for q in overlaps:
                    model = identify(data, library, refine=False, derivative=WeakForm(overlap=q))
                    fits[q].append(_terms(model, system))
                    n_rows[q] = model.equations[1].n_rows
            crb = {name: np.mean([f[name][1] for f in oe if f]) for name in truth}
            for q in overlaps:
                good = [f for f in fits[q] if f]
                if good:
                    rel = [(f[name][0] - truth[name]) / crb[name] for f in good for name in truth]
                    own = [(f[name][0] - truth[name]) / f[name][1] for f in good for name in truth]
                    eff, zstd = f"{np.sqrt(np.mean(np.square(rel))):.3g}", f"{np.std(own):.3g}"
                else:
                    eff = zstd = "-"
                rows.append([kind, forcing, q, f"{len(good)}/{seeds}", eff, zstd, n_rows[q]])
            good = [f for f in oe if f]
            rel = [(f[name][0] - truth[name]) / crb[name] for f in good for name in truth]
            rows.append(
                [
                    kind,
                    forcing,
                    "output error",
                    f"{len(good)}/{seeds}",
                    f"{np.sqrt(np.mean(np.square(rel))):.3g}",
                    "-",
                    "-",
                ]
            )
            table(f"{kind}, {forcing}", HEADER, rows[-len(overlaps) - 1 :])
    return rows


PAPER_HEADER = ["system", "forcing", "overlap", "exact", "median largest error", "spurious terms met"]


def _paper_cases(seeds):
    """(system, forcing label, seed, clean record, library, noise) of ``--part paper``."""
    for name, (build, kwargs) in CASES.items():
        system = build(**kwargs)
        library = paper(system.states, system.inputs, degree=4 if name.startswith("Bouc") else 6)
        for forcing in ("sine", "multisine"):
            for seed in range(seeds):
                signal = Sine(100.0, 10.0) if forcing == "sine" else Multisine(60.0, 2.0, 30.0, seed=10 + seed)
                record = simulate(system, time_grid(2.0, 32768), inputs=signal)
                yield name, system, forcing, seed, record, library, 0.004
    x1, x2, F = symbols("x1 x2 F")
    system = OdeSystem((x1, x2), (F,), (x2, (F - 3.0 * x2 - 2e3 * x1 - 2e7 * x1**3) / 0.5), name="duffing")
    for seed in range(seeds):
        signal = Multisine(10.0, 1.0, 30.0, seed=5 + seed, period=5.0)
        yield (
            "Duffing at 400 Hz",
            system,
            "multisine",
            seed,
            simulate(system, time_grid(10.0, 400), inputs=signal),
            paper([x1, x2], [F], degree=3),
            0.01,
        )


def run_paper(seeds, overlaps):
    groups = {}
    for name, system, forcing, seed, clean, library, noise in _paper_cases(seeds):
        data = clean.with_noise(noise, seed=seed)
        for q in overlaps:
            truth = compare_to_truth(identify(data, library, refine=False, derivative=WeakForm(overlap=q)), system)
            exact, largest, spurious = groups.setdefault((name, forcing, q), ([], [], Counter()))
            exact.append(truth.exact_support)
            if truth.exact_support:
                largest.append(truth.max_error())
            spurious.update(t for terms in truth.spurious.values() for t in terms)
    rows = [
        [
            name,
            forcing,
            q,
            f"{sum(exact)}/{len(exact)}",
            f"{np.median(largest):.2g}" if largest else "-",
            ", ".join(f"{t} ({n})" for t, n in spurious.most_common(3)) or "-",
        ]
        for (name, forcing, q), (exact, largest, spurious) in groups.items()
    ]
    table(
        f"Equation error on the paper's systems, windows apart (1) or overlapping (q), {seeds} seeds",
        PAPER_HEADER,
        rows,
    )
    return rows


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--part", choices=["oscillators", "paper"], default="oscillators")
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--overlaps", default="1,2,3")
    args = p.parse_args()
    overlaps = [int(q) for q in args.overlaps.split(",")]
    if args.part == "paper":
        with one_blas_thread():
            run_paper(args.seeds, overlaps)
        write_page("weakform-paper", __doc__)
        return
    with one_blas_thread():
        rows = run(args.seeds, overlaps)
    table(f"Equation error with windows apart (1) or overlapping (q), {args.seeds} seeds", HEADER, rows)
    write_page("weakform-oscillators", __doc__)


if __name__ == "__main__":
    main()
