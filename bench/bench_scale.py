"""Speed and memory as the record grows: streaming identification, the RVM against scikit-learn's
ARDRegression, Dask against the single process, and a batch of records.

Data: the paper's Duffing oscillator (m=1, c=20, k=1e4, k3=1e9) driven by 100 N at 10 Hz, sampled
at 32768 Hz, 0.4 % noise on the states. The 10^7-sample record (305 s) is simulated in pieces of
2^20 samples (fixed-step RK4 compiled with CasADi, the state carried from piece to piece) and
written column by column to disk, then identified from a memory-mapped NPZ: neither the record nor
a dense N x M dictionary is ever held. Library: Eq. 21 at degree 3 (34 terms over x1, x2, F).

Peak memory is tracemalloc's peak over the call (numpy and Python allocations; the memory-mapped
input pages are not counted, they are the operating system's page cache).

Run: ``PYTHONPATH=. python bench/bench_scale.py [--max-n 1e7] [--skip-dask]``
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
import tracemalloc
import warnings
import zipfile
from pathlib import Path

import numpy as np
from _report import table, timed, write_page  # noqa: E402  (bench/ is on sys.path when run as a script)

from symsbl import (
    RVM,
    Evaluator,
    Sine,
    WeakForm,
    identify,
    identify_many,
    identify_stream,
    open_npz,
    paper,
    simulate,
    stream_stats,
    symbols,
    systems,
)

FS = 32768
PIECE = 2**20
NOISE = 0.004
LIB = paper(symbols("x1 x2"), symbols("F"), degree=3)
NAMES = dict(states=("x1", "x2"), inputs=("F",))


def write_record(directory: Path, n: int, seed: int = 0) -> Path:
    """Simulate ``n`` samples piece by piece into ``t.npy`` ... and an uncompressed NPZ of them."""
    cols = {k: np.lib.format.open_memmap(directory / f"{k}.npy", mode="w+", shape=(n,)) for k in ("t", "x1", "x2", "F")}
    rng = np.random.default_rng(seed)
    system, force = systems.duffing(), Sine(100.0, 10.0)
    x0, a, scale = np.zeros(2), 0, None
    while a < n:
        b = min(a + PIECE, n)
        t = np.arange(a, b + 1) / FS  # one extra sample: the next piece starts from its state
        sim = simulate(system, t, inputs=force, x0=x0, method="rk4", jit=True)
        x0 = sim.states[-1]
        states = sim.states[:-1]
        if scale is None:
            scale = NOISE * states.std(axis=0)
        noisy = states + scale * rng.standard_normal(states.shape)
        cols["t"][a:b], cols["x1"][a:b], cols["x2"][a:b] = t[:-1], noisy[:, 0], noisy[:, 1]
        cols["F"][a:b] = sim.inputs[:-1, 0]
        a = b
    for mm in cols.values():
        mm.flush()
    path = directory / "duffing.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for k in cols:
            zf.write(directory / f"{k}.npy", arcname=f"{k}.npy")
    return path


def measured(fn):
    """(result, seconds, tracemalloc peak in MiB)."""
    tracemalloc.start()
    t0 = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return out, dt, peak


def x2_support(model):
    return ", ".join(t.name for t in model.equation("x2").terms)


def scaling(path: Path, sizes):
    from symsbl import fit_stats

    rows = []
    identify_stream(open_npz(path, **NAMES, stop=20000), LIB)  # compile the dictionary once
    for n in sizes:

        def run(n_jobs, n=n):
            problem = stream_stats(open_npz(path, **NAMES, stop=n), LIB, n_jobs=n_jobs)
            t0 = time.perf_counter()
            return fit_stats(problem), time.perf_counter() - t0

        (model, t_fit), dt, peak = measured(lambda: run(1))
        (_, t_fit2), dt2, peak2 = measured(lambda: run(2))
        ref = "not run (the record alone is 320 MB)"
        if n <= 10**6:
            traj = _trajectory(path, n)
            _, dtm, peakm = measured(lambda traj=traj: identify(traj, LIB))
            ref = f"{dtm:.2f} s / {peakm:.0f} MiB"
        rows.append(
            [
                f"{n:.0e}",
                f"{dt:.2f}",
                f"{dt - t_fit:.2f}",
                f"{1e9 * (dt - t_fit) / n:.0f}",
                f"{t_fit:.2f}",
                f"{peak:.0f}",
                f"{dt2 - t_fit2:.2f}",
                f"{peak2:.0f}",
                ref,
                x2_support(model),
            ]
        )
    table(
        "Streaming identification from a memory-mapped NPZ (Eq. 21, degree 3, 34 terms; weak form)",
        [
            "N",
            "total (s)",
            "statistics (s)",
            "statistics ns/sample",
            "fit (s)",
            "peak (MiB)",
            "statistics, n_jobs=2 (s)",
            "peak, n_jobs=2 (MiB)",
            "in-memory identify(): time / peak",
            "x2' support found",
        ],
        rows,
    )


def _trajectory(path: Path, n: int):
    from symsbl import Trajectory

    with np.load(path) as z:
        return Trajectory(
            z["t"][:n], np.column_stack([z["x1"][:n], z["x2"][:n]]), z["F"][:n][:, None], ("x1", "x2"), ("F",)
        )


def rvm_vs_ard(path: Path, sizes):
    from sklearn.linear_model import ARDRegression

    rows = []
    evaluator = Evaluator(LIB)
    for n in sizes:
        traj = _trajectory(path, n)
        diff = WeakForm().resolve(traj.t, traj.states, n_terms=len(LIB))
        Z = np.column_stack([traj.column(v) for v in LIB.variable_names])
        D = diff.reduce(evaluator.evaluate(Z))
        y = diff.targets(traj.t, traj.states)[:, 1]
        scale = np.linalg.norm(D, axis=0)
        Dn = D / scale  # ARD's prior is not scale-invariant: give it unit-norm columns
        rvm, t_rvm = timed(lambda D=D, y=y: RVM().fit(D, y))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ard, t_ard = timed(lambda Dn=Dn, y=y: ARDRegression(fit_intercept=False).fit(Dn, y))
        s_rvm = sorted(LIB.names[i] for i in rvm.active_)
        s_ard = sorted(LIB.names[i] for i in np.flatnonzero(np.abs(ard.coef_) > 0))
        rows.append(
            [
                f"{n:.0e}",
                f"{len(D)} x {D.shape[1]}",
                f"{1e3 * t_rvm:.1f}",
                f"{1e3 * t_ard:.1f}",
                f"{t_ard / t_rvm:.1f}",
                ", ".join(s_rvm),
                f"{len(s_ard)} terms",
            ]
        )
    table(
        "RVM (symsbl, plain fit without the support search) against sklearn ARDRegression on the same weak-form "
        "rows of x2'",
        ["N samples", "rows x terms", "RVM (ms)", "ARD (ms)", "ARD / RVM", "RVM support", "ARD support"],
        rows,
    )


def _load_block(directory: Path, a: int, b: int) -> np.ndarray:
    return np.column_stack([np.load(directory / f"{k}.npy", mmap_mode="r")[a:b] for k in ("t", "x1", "x2", "F")])


def dask_vs_single(directory: Path, path: Path, n: int):
    import dask
    from dask.distributed import Client, LocalCluster

    from symsbl import fit_stats, from_delayed, identify_dask

    t0 = time.perf_counter()
    problem = stream_stats(open_npz(path, **NAMES, stop=n), LIB)
    single = fit_stats(problem)
    t_single = time.perf_counter() - t0
    cuts = list(range(0, n, 2**20)) + [n]
    parts = [dask.delayed(_load_block)(directory, a, b) for a, b in zip(cuts[:-1], cuts[1:])]
    record = from_delayed(parts, n_columns=4, lengths=np.diff(cuts))
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
        Client(cluster),
    ):
        identify_dask(record[:50000], LIB, **NAMES, refine=False)  # warm the workers
        # the map-reduce of the statistics against the single pass: both by equation error
        model, t_dask = timed(lambda: identify_dask(record, LIB, **NAMES, refine=False), repeats=1)
    assert model.metadata["n_rows"] == single.metadata["n_rows"]
    worst = max(
        float(np.max(np.abs(a.coefs - b.coefs) / np.abs(b.coefs))) if len(b.coefs) else 0.0
        for a, b in zip(model.equations, single.equations)
    )
    same = all(a.names == b.names for a, b in zip(model.equations, single.equations))
    table(
        f"Dask (LocalCluster, 2 workers x 1 thread, in-process) against the single process, N = {n:.0e}, "
        f"window {problem.derivative.window} samples",
        ["single process (s)", "Dask (s)", "Dask / single", "same supports", "max relative coefficient difference"],
        [[f"{t_single:.2f}", f"{t_dask:.2f}", f"{t_dask / t_single:.2f}", same, f"{worst:.1e}"]],
    )


def batch(path: Path):
    records = [_trajectory(path, 2**17).slice(0, 2**17)]
    with np.load(path) as z:
        for k in range(1, 8):
            a = k * 2**17
            from symsbl import Trajectory

            records.append(
                Trajectory(
                    z["t"][a : a + 2**17],
                    np.column_stack([z["x1"][a : a + 2**17], z["x2"][a : a + 2**17]]),
                    z["F"][a : a + 2**17][:, None],
                    ("x1", "x2"),
                    ("F",),
                )
            )
    loop, t_loop = timed(lambda: [identify(r, LIB) for r in records], repeats=2)
    many, t_many = timed(lambda: identify_many(records, LIB, n_jobs=2), repeats=2)
    assert all(str(a) == str(b) for a, b in zip(loop, many))
    table(
        "A batch of 8 records of 4 s each",
        ["loop of identify (s)", "identify_many, 2 threads (s)", "loop / batch"],
        [[f"{t_loop:.2f}", f"{t_many:.2f}", f"{t_loop / t_many:.2f}"]],
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--max-n", type=float, default=1e7)
    parser.add_argument("--skip-dask", action="store_true")
    args = parser.parse_args()
    n_max = int(args.max_n)
    sizes = [n for n in (10**4, 10**5, 10**6, 10**7) if n <= n_max]
    with tempfile.TemporaryDirectory(prefix="symsbl_bench_") as tmp:
        directory = Path(tmp)
        t0 = time.perf_counter()
        path = write_record(directory, n_max)
        print(
            f"simulated and wrote {n_max:.0e} samples ({n_max / FS:.0f} s of Duffing at {FS} Hz) in "
            f"{time.perf_counter() - t0:.1f} s"
        )
        scaling(path, sizes)
        rvm_vs_ard(path, [n for n in sizes if n <= 10**6])
        batch(path)
        if not args.skip_dask:
            dask_vs_single(directory, path, n_max)
    print(f"\nprocess peak resident memory: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")
    write_page("scale", __doc__)


if __name__ == "__main__":
    main()
