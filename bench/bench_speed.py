"""Where users wait: ``symsbl demo``, a 10^7-sample record identified by output error, the fast test tier.

1. **``symsbl demo``** (the paper's five systems, 3 s at 32768 Hz, Eq. 21 to degree 6, output error and the
   validated model choice), run as a user runs it: a fresh subprocess, imports and compilation included. Its
   CPU time (user + system, the subprocess's ``RUSAGE_CHILDREN``, gcc's compilations included), with an empty
   compilation cache (``XDG_CACHE_HOME``: a newcomer's first run) and again with the cache it left, and wall
   time against earlier measurements
   of the same command on this machine kind: main before these changes (commit e0af554, 54.1 s of CPU,
   ``/usr/bin/time``, load average 2-3) and an earlier measurement from before the validated model choice landed
   (24 s of CPU). Its printed models and table, timings taken out, are compared line by line with the output
   of commit e0af554 (``bench/demo_reference.txt``).
2. **A 10^7-sample Duffing record** (:mod:`bench_refine`'s part 3: multisine 60 N rms 2-30 Hz, 32768 Hz, 1 %
   noise, written once to an uncompressed NPZ), identified with the defaults,
   ``identify_stream(open_npz(path, ...), polynomial([x1, x2], 3) + inputs([F]))``, each in a fresh subprocess
   in one BLAS thread: now, and with the model path fitted on every sample refined on (``PATH_SAMPLES`` set
   past the record, the previous behaviour), so that the ratio is measured in one run. Earlier measurements:
   7.9 s before the noise model, residual tests and model path landed; 52 s (49 s of CPU) on main before
   these changes, measured earlier on a quiet machine.
3. **The fast tier from a fresh clone** (``--tier``): ``git clone`` of this checkout's HEAD into a temporary
   folder, an empty compilation cache (``XDG_CACHE_HOME``), then ``python -m pytest -m "not slow"`` there (two
   xdist workers on two cores), timed from outside.

The machine is shared: CPU times move less with the load than wall times do; the load average is printed.

Run: ``PYTHONPATH=. python bench/bench_speed.py [--tier] [--skip-demo] [--skip-long]``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _report import ROOT, one_blas_thread, table, write_page  # noqa: E402  (bench/ is on sys.path as a script)

#: ``symsbl demo`` on main before these changes (commit e0af554): CPU seconds, ``/usr/bin/time``, load 2-3.
DEMO_MAIN_CPU = 54.1
#: The same command before the validated model choice landed (CPU seconds, an earlier measurement).
DEMO_BEFORE_CHOICE_CPU = 24.0
#: 10^7 samples before the noise model, residual tests and model path landed (seconds, an earlier measurement).
LONG_BEFORE_PATH = 7.9
#: 10^7 samples on main before these changes (seconds of wall and CPU, an earlier measurement, quiet machine).
LONG_MAIN, LONG_MAIN_CPU = 52.0, 49.0
REFERENCE = Path(__file__).resolve().parent / "demo_reference.txt"


def _env() -> dict:
    return dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _run(cmd, **kw) -> tuple[subprocess.CompletedProcess, float, float]:
    """``cmd`` in a subprocess: the completed process, its wall and CPU seconds (itself and its children)."""
    cpu0, t0 = _children_cpu(), time.perf_counter()
    done = subprocess.run(cmd, check=False, capture_output=True, text=True, **kw)
    return done, time.perf_counter() - t0, _children_cpu() - cpu0


def _untimed(text: str) -> list[str]:
    """The demo's lines with the table's time column taken out."""
    return [re.sub(r"\s+[0-9.]+s$", "", line) for line in text.splitlines()]


def demo() -> None:
    with tempfile.TemporaryDirectory(prefix="symsbl_bench_demo_") as cache:
        env = dict(_env(), XDG_CACHE_HOME=cache)
        runs = [_run([sys.executable, "-m", "symsbl", "demo"], env=env) for _ in range(2)]  # empty cache, then kept
    failed = [done for done, _, _ in runs if done.returncode != 0]
    if failed:
        print(f"\nsymsbl demo failed (exit {failed[0].returncode}):\n{failed[0].stderr[-3000:]}")
        return
    reference = _untimed(REFERENCE.read_text())
    table(
        "symsbl demo, fresh subprocess (CPU: user + system, compilation included)",
        ["compilation cache", "CPU (s)", "wall (s)", "main before (CPU s)", "before / now",
         "before the model choice (CPU s)", "now / that", "models and table as before"],
        [[label, f"{cpu:.1f}", f"{wall:.1f}", DEMO_MAIN_CPU, f"{DEMO_MAIN_CPU / cpu:.2f}", DEMO_BEFORE_CHOICE_CPU,
          f"{cpu / DEMO_BEFORE_CHOICE_CPU:.2f}", "yes" if _untimed(done.stdout) == reference else "NO"]
         for label, (done, wall, cpu) in zip(("empty (a first run)", "kept from the first"), runs)],
    )  # fmt: skip
    print("\n" + "\n".join(line for line in runs[0][0].stdout.splitlines() if re.search(r"\s[0-9.]+s$", line)))


def long_child(path: str, path_samples: int | None) -> None:
    """In a subprocess: identify the NPZ record with the defaults; print one JSON line."""
    import bench_refine as br

    import symsbl._refine.path as model_path
    from symsbl import identify_stream, open_npz

    if path_samples is not None:
        model_path.PATH_SAMPLES = path_samples
    with one_blas_thread():
        cpu0, t0 = time.process_time(), time.perf_counter()
        model = identify_stream(open_npz(path, **br.NAMES), br.LIB)
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    info = model.metadata.get("refine", {})
    out = dict(wall=wall, cpu=cpu, model=str(model), passes=info.get("passes"), samples=info.get("samples"))
    print(json.dumps(out))


def long_record(n: int) -> None:
    import bench_refine as br

    with tempfile.TemporaryDirectory(prefix="symsbl_bench_speed_") as tmp:
        t0 = time.perf_counter()
        path = br.write_record(Path(tmp), n)
        print(f"\nsimulated and wrote {n:.0e} samples in {time.perf_counter() - t0:.1f} s (not timed below)")
        runs = {}
        for name, samples in (("now", None), ("path on every sample", 2**62)):
            cmd = [sys.executable, __file__, "--long-child", str(path)]
            cmd += [] if samples is None else ["--path-samples", str(samples)]
            done, wall, cpu = _run(cmd, env=_env())
            if done.returncode != 0:
                print(f"\n{name}: the subprocess failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
                return
            runs[name] = (json.loads(done.stdout.strip().splitlines()[-1]), wall, cpu)
    now, old = runs["now"][0], runs["path on every sample"][0]
    rows = [
        [name, f"{r['wall']:.1f}", f"{r['cpu']:.1f}", f"{wall:.1f}", f"{cpu:.1f}", r["passes"], r["samples"]]
        for name, (r, wall, cpu) in runs.items()
    ]
    table(
        f"identify_stream on {n:.0e} samples, fresh subprocesses, one BLAS thread",
        ["model path", "call (s)", "call CPU (s)", "process (s)", "process CPU (s)", "passes", "refined on"],
        rows,
    )
    table(
        "Ratios of the call's time",
        ["path on every sample / now", f"main before ({LONG_MAIN:g} s) / now", f"now / before the path "
         f"({LONG_BEFORE_PATH:g} s)", "same model"],
        [[f"{old['wall'] / now['wall']:.2f}", f"{LONG_MAIN / now['wall']:.2f}",
          f"{now['wall'] / LONG_BEFORE_PATH:.2f}", "yes" if now["model"] == old["model"] else "NO"]],
    )  # fmt: skip
    print(f"\nmodel:\n{now['model']}")


def tier() -> None:
    with tempfile.TemporaryDirectory(prefix="symsbl_bench_tier_") as tmp:
        clone = Path(tmp) / "clone"
        subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
        head = subprocess.run(["git", "-C", str(clone), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
        env = dict(os.environ, XDG_CACHE_HOME=str(Path(tmp) / "cache"))
        env.pop("PYTHONPATH", None)
        cmd = [sys.executable, "-m", "pytest", "-m", "not slow", "-q", "-p", "no:cacheprovider", "--durations=15"]
        done, wall, cpu = _run(cmd, cwd=clone, env=env)
    lines = done.stdout.strip().splitlines()
    closing = lines[-1] if lines else done.stderr[-500:]
    table(
        f"Fast tier from a fresh clone of commit {head.stdout.strip()}, empty compilation cache",
        ["wall (min)", "CPU (min)", "result"],
        [[f"{wall / 60:.1f}", f"{cpu / 60:.1f}", closing.strip("= ")]],
    )
    slowest = [line for line in lines if re.match(r"^[0-9.]+s (call|setup|teardown)", line)]
    print("\nslowest:\n" + "\n".join(slowest))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-demo", action="store_true")
    parser.add_argument("--skip-long", action="store_true")
    parser.add_argument("--tier", action="store_true", help="also time the fast tier from a fresh clone")
    parser.add_argument("--samples", type=float, default=1e7, help="samples of part 2's record")
    parser.add_argument("--long-child", help=argparse.SUPPRESS)
    parser.add_argument("--path-samples", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.long_child:
        long_child(args.long_child, args.path_samples)
        return
    print(f"load average at start: {', '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)")
    if not args.skip_demo:
        demo()
    if not args.skip_long:
        long_record(int(args.samples))
    if args.tier:
        tier()
    write_page("speed", __doc__)


if __name__ == "__main__":
    main()
