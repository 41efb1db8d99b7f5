"""Where the time of ``identify`` goes as a chain of N masses grows: N = 2, 3, 5 (and 10).

System: N masses in a chain, the first tied to the ground, states ``x1..xN`` (positions, m) and ``v1..vN``
(velocities, m/s). Mass ``i`` (1.0-1.5 kg) is tied to mass ``i - 1`` (the ground for ``i = 1``) by a spring
(2e3-5e3 N/m) and a dashpot of 0.5 % of the critical damping of that spring on that mass; the values of mass ``i``
are drawn once (seed 11) and do not depend on N. Two cubic springs: ``kg x1^3`` between the ground and mass 1 and
``kc (xN - x(N-1))^3`` between masses N - 1 and N, each scaled so that its force at one standard deviation of
the linear response's stretch is 20 % of the linear spring's (the nonlinearity is as visible at every N). A
random-phase multisine force (20 N rms, 1-30 Hz, seed 3, one period) acts on the last mass; the record is 4 s at
1024 Hz (4097 samples) while its weak-form rows (a quarter of the samples) number at least twice the candidates,
else doubled until they do (16 s at N = 10), simulated by CVODES, every position and velocity measured with
0.5 % noise (seed 0). Identification: ``identify(record, polynomial(states, 3) + inputs([F]),
kinematics="x1:v1,...")``, the defaults otherwise (weak-form equation error, RVM, output-error refinement with
its term selection). The library grows as ``C(2N + 3, 3) + 1`` terms: 36, 85, 287 (1772 at N = 10).
With ``--measured positions`` (page *mdof-positions*) the record holds the positions alone (``states=`` names
the velocities too); with ``--measured accelerations`` (page *mdof-accelerations*) the accelerations alone
(``kinematics="x1:v1:a1,..."``; the noise-free ones from the simulated states, 0.5 % of each one's RMS added,
seed 0).

Measured in one process, in order of N, with an empty compilation cache (``SYMSBL_JIT_CACHE`` set to a fresh
folder, so every compiled function is compiled in the run), one BLAS thread:

- CPU (user + system of the process and of its children, the C compiler) and wall time of ``identify``;
- the equation error (everything outside the refinement) and the refinement (``refine_or_keep``), by wrapping
  the functions that do them; ``metadata["refine"]`` gives the refinement's own seconds and rounds;
- exclusive CPU time of stages (a stage nested in another counts for the inner one only): compilation
  (``symsbl._base.jit._compile``: C code generation, gcc, loading), and the forward sensitivities
  (``symsbl._refine.sensitivity``): building the SX step and its ``mapaccum`` (``sensitivity_step``,
  ``state_step``, ``_chunk``), the pass's calls through ``Function.buffer`` (compiled C, or CasADi's virtual
  machine when ``jit="auto"`` declines a C source over the refinement's bound, ``FIT_SOURCE``) and the numpy work of
  ``Passes.sensitivities`` around them (whitening, the Gauss-Newton blocks); "rest" is everything else
  (the RVM, the solver's linear algebra, the screen, the model choice). Shares are of the CPU of ``identify``;
- the C sources generated (their sizes) and which of the refinement's passes ran compiled;
- terms missing and spurious against the true equations (``compare_to_truth``);
- the process's peak resident memory after each N (``getrusage``: a running maximum, so each row is the peak
  up to and including that N).

The growth exponent ``p`` of ``time ~ N^p`` is the least-squares slope of log time against log N over the
measured N, and between consecutive N. The largest N is identified once more, caches emptied, with
``refine_options={"jit": True}``, which compiles every pass whatever the size of its C source: what compiling
would cost and save there. Then, caches emptied again, it is run under ``cProfile`` and the functions with the
most cumulative and own time are listed (a call into compiled code or CasADi's virtual machine is one C call
to the profiler: its time is the caller's own; the script's timers add under 1 %).

Run: ``PYTHONPATH=. python bench/bench_mdof.py [--big] [--sizes 2,3,5] [--no-compiled] [--no-profile]``.
"""

from __future__ import annotations

import argparse
import cProfile
import functools
import io
import math
import os
import pstats
import re
import resource
import tempfile
import time
from contextlib import contextmanager

import casadi as ca
import numpy as np
from _report import one_blas_thread, table, write_page  # noqa: E402  (bench/ is on sys.path as a script)

import symsbl
import symsbl._identify as _identify_module
from symsbl import Multisine, OdeSystem, Trajectory, compare_to_truth, identify, simulate, symbols, time_grid
from symsbl._base import jit as _jit
from symsbl._refine import sensitivity as _sensitivity

FS = 1024
SECONDS = 4.0
NOISE = 0.005
ZETA = 0.005
#: Force of a cubic spring at one standard deviation of its stretch, as a share of the linear spring's.
CUBIC_SHARE = 0.2
FORCE = dict(rms=20.0, f_min=1.0, f_max=30.0, seed=3)
#: What the record holds: every state, the positions alone, or the accelerations alone.
MEASURED = ("all", "positions", "accelerations")
MAX_N = 10
_rng = np.random.default_rng(11)
MASSES = _rng.uniform(1.0, 1.5, MAX_N)
SPRINGS = _rng.uniform(2e3, 5e3, MAX_N)
DAMPERS = 2 * ZETA * np.sqrt(SPRINGS * MASSES)


def chain(n: int, kg: float = 0.0, kc: float = 0.0) -> OdeSystem:
    """The chain of ``n`` masses with cubic springs ``kg`` (ground to mass 1) and ``kc`` (masses n - 1 and n)."""
    x = list(symbols(" ".join(f"x{i + 1}" for i in range(n))))
    v = list(symbols(" ".join(f"v{i + 1}" for i in range(n))))
    (F,) = symbols("F")
    m, k, c = MASSES[:n], SPRINGS[:n], DAMPERS[:n]

    def link(i):  # force of link i (mass i - 1 to mass i; ground for i = 0) on mass i
        dx = x[i] - (x[i - 1] if i else 0)
        dv = v[i] - (v[i - 1] if i else 0)
        return -k[i] * dx - c[i] * dv

    force = [link(i) for i in range(n)]
    force[0] = force[0] - kg * x[0] ** 3
    force[-1] = force[-1] - kc * (x[-1] - x[-2]) ** 3 + F
    force[-2] = force[-2] + kc * (x[-1] - x[-2]) ** 3
    for i in range(n - 1):  # each link pulls the mass before it the other way
        force[i] = force[i] - link(i + 1)
    accel = [force[i] / m[i] for i in range(n)]
    return OdeSystem(tuple(x + v), (F,), tuple(v + accel), name=f"chain of {n}")


def damping_ratios(n: int) -> tuple[float, float]:
    """The smallest and largest modal damping ratio of the linear chain."""
    system = chain(n)
    jacobian = ca.jacobian(ca.vertcat(*system.rhs), ca.vertcat(*system.states))
    A = np.array(ca.evalf(ca.substitute(jacobian, system.inputs[0], 0.0)))
    lam = np.linalg.eigvals(A)
    lam = lam[lam.imag > 0]
    zeta = -lam.real / np.abs(lam)
    return float(zeta.min()), float(zeta.max())


def seconds(n: int) -> float:
    """The record's length for ``n`` masses: :data:`SECONDS`, doubled until its weak-form rows (a quarter of its
    samples) number at least twice the library's ``C(2n + 3, 3) + 1`` candidates."""
    length = SECONDS
    while FS * length / 4 < 2 * (math.comb(2 * n + 3, 3) + 1):
        length *= 2
    return length


def system_and_record(n: int):
    """The chain of ``n`` with its cubic springs scaled on the linear response, and the noisy record."""
    length = seconds(n)
    t = time_grid(length, FS)
    force = Multisine(**FORCE, period=length)
    linear = simulate(chain(n), t, inputs=force)
    col = {name: linear.states[:, j] for j, name in enumerate(linear.state_names)}
    kg = CUBIC_SHARE * SPRINGS[0] / np.std(col["x1"]) ** 2
    kc = CUBIC_SHARE * SPRINGS[n - 1] / np.std(col[f"x{n}"] - col[f"x{n - 1}"]) ** 2
    system = chain(n, kg, kc)
    clean = simulate(system, t, inputs=force)
    return system, clean.with_noise(NOISE, seed=0), (kg, kc), clean


def observed(n: int, measured: str = "all"):
    """The system, the record as ``measured`` (see :data:`MEASURED`), the options of ``identify`` that name
    its states, and the cubic springs."""
    system, record, springs, clean = system_and_record(n)
    names = [str(s) for s in system.states]
    pairs = ",".join(f"x{i + 1}:v{i + 1}" for i in range(n))
    if measured == "all":
        return system, record, dict(kinematics=pairs), springs
    if measured == "positions":
        columns, labels, kinematics = record.states[:, :n], names[:n], pairs
    else:
        accel = np.asarray(system.evaluate_rhs(clean.states, clean.inputs))[:, n:]
        rng = np.random.default_rng(0)
        columns = accel + NOISE * accel.std(axis=0) * rng.standard_normal(accel.shape)
        labels = [f"a{i + 1}" for i in range(n)]
        kinematics = ",".join(f"x{i + 1}:v{i + 1}:a{i + 1}" for i in range(n))
    trajectory = Trajectory(record.t, columns, record.inputs, tuple(labels), tuple(record.input_names))
    return system, trajectory, dict(kinematics=kinematics, states=names), springs


# -- timers -----------------------------------------------------------------------------------------------------


def _cpu() -> float:
    """CPU seconds of this process and its finished children (the C compiler runs as a child)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


class Stages:
    """Exclusive CPU and wall time of named stages: time spent in a stage nested inside another is the inner's."""

    def __init__(self):
        self.cpu, self.wall, self.calls = {}, {}, {}
        self._stack = []  # [name, cpu at (re)entry, wall at (re)entry]

    def reset(self):
        for kept in (self.cpu, self.wall, self.calls):
            kept.clear()

    def _charge(self, frame, cpu, wall):
        name = frame[0]
        self.cpu[name] = self.cpu.get(name, 0.0) + cpu - frame[1]
        self.wall[name] = self.wall.get(name, 0.0) + wall - frame[2]

    @contextmanager
    def stage(self, name):
        cpu, wall = _cpu(), time.perf_counter()
        if self._stack:
            self._charge(self._stack[-1], cpu, wall)
        self._stack.append([name, cpu, wall])
        self.calls[name] = self.calls.get(name, 0) + 1
        try:
            yield
        finally:
            cpu, wall = _cpu(), time.perf_counter()
            self._charge(self._stack.pop(), cpu, wall)
            if self._stack:
                self._stack[-1][1:] = [cpu, wall]

    def within(self, name) -> bool:
        return any(frame[0] == name for frame in self._stack)

    def wrap(self, owner, attribute, name):
        """Replace ``owner.attribute`` by the same function timed as stage ``name`` (or ``name()``, when called)."""
        fn = getattr(owner, attribute)

        @functools.wraps(fn)
        def timed(*args, **kwargs):
            with self.stage(name() if callable(name) else name):
                return fn(*args, **kwargs)

        setattr(owner, attribute, timed)


STAGES = Stages()
COMPILE = ("compile (equation error)", "compile (refinement)")
SENSITIVITY = (
    "sensitivity build",
    "sensitivity calls, compiled",
    "sensitivity calls, virtual machine",
    "sensitivity blocks",
)
EE_STAGES = ("equation error, rest", "compile (equation error)")
REFINE_STAGES = ("refinement, rest", "compile (refinement)", *SENSITIVITY, "plain simulation")
#: The output-error models ``refine_or_keep`` returned since the last reset (``identify`` may report another).
REFINED: list = []
#: The C sources generated since the last reset: ``[(function name, bytes)]``.
SOURCES: list = []
#: How the refinement's passes run since the last reset: ``[(name, compiled)]``.
PASSES: list = []
#: The sensitivity passes built since the last reset: ``[(free coefficients, samples per call, compiled)]``.
SIZES: list = []


def _capture(refine_or_keep):
    @functools.wraps(refine_or_keep)
    def captured(*args, **kwargs):
        out = refine_or_keep(*args, **kwargs)
        REFINED.append(out)
        return out

    return captured


def _record_source(source):
    @functools.wraps(source)
    def recorded(fn):
        code, why = source(fn)
        SOURCES.append((fn.name(), len(code)))
        return code, why

    return recorded


def _record_wrap(jit_wrap):
    @functools.wraps(jit_wrap)
    def recorded(fn, name, *args, **kwargs):
        out = jit_wrap(fn, name, *args, **kwargs)
        PASSES.append((fn.name(), out[1]))
        return out

    return recorded


def _timed_calls(init):
    """``Passes.__init__``, then its sensitivity pass's call timed as a stage of its own (compiled or not)."""

    @functools.wraps(init)
    def timed_init(self, *args, **kwargs):
        before = len(PASSES)
        init(self, *args, **kwargs)
        compiled = PASSES[-1][1] if len(PASSES) > before else True  # else found compiled in memory
        SIZES.append((self.layout["npar"], self.chunk, compiled))
        buf, call = self._sens_buffer
        name = "sensitivity calls, compiled" if compiled else "sensitivity calls, virtual machine"

        def timed_call():
            with STAGES.stage(name):
                return call()

        self._sens_buffer = (buf, timed_call)

    return timed_init


def _instrument() -> None:
    """Time and record the stages by wrapping the functions that do them (symsbl itself is not changed)."""
    _identify_module.refine_or_keep = _capture(_identify_module.refine_or_keep)
    STAGES.wrap(_identify_module, "refine_or_keep", "refinement, rest")
    STAGES.wrap(
        _jit,
        "_compile",
        lambda: "compile (refinement)" if STAGES.within("refinement, rest") else "compile (equation error)",
    )
    for name in ("sensitivity_step", "state_step", "_chunk"):
        STAGES.wrap(_sensitivity, name, "sensitivity build")
    STAGES.wrap(_sensitivity.Passes, "sensitivities", "sensitivity blocks")
    STAGES.wrap(_sensitivity.Passes, "simulate", "plain simulation")
    _jit._source = _record_source(_jit._source)
    _sensitivity.jit_wrap = _record_wrap(_sensitivity.jit_wrap)
    _sensitivity.Passes.__init__ = _timed_calls(_sensitivity.Passes.__init__)


def _empty_caches(folder: str) -> None:
    """A fresh compilation cache on disk, and nothing kept in memory: every function is built and compiled again."""
    os.environ[_jit.CACHE_ENV] = folder
    _jit._MEMORY.clear()
    _jit._SEEN.clear()
    _sensitivity._VM_CHUNKS.clear()


def _terms(truth) -> tuple[list[str], list[str]]:
    missing = [f"{lhs}: {t}" for lhs, terms in truth.missing.items() for t in terms]
    spurious = [f"{lhs}: {t}" for lhs, terms in truth.spurious.items() for t in terms]
    return missing, spurious


def run(n: int, jit="auto", measured: str = "all") -> dict:
    system, record, naming, (kg, kc) = observed(n, measured)
    library = symsbl.polynomial(list(system.states), 3) + symsbl.inputs(list(system.inputs))
    STAGES.reset()
    for kept in (SOURCES, PASSES, SIZES, REFINED):
        kept.clear()
    with one_blas_thread():
        cpu0, t0 = _cpu(), time.perf_counter()
        with STAGES.stage("equation error, rest"):
            model = identify(record, library, **naming, refine_options={"jit": jit})
        wall, cpu = time.perf_counter() - t0, _cpu() - cpu0
    info = model.metadata.get("refine", {})
    missing, spurious = _terms(compare_to_truth(model, system))
    oe = [m for m in REFINED if m.fit is symsbl.FitMethod.OUTPUT_ERROR]
    oe_missing, oe_spurious = _terms(compare_to_truth(oe[-1], system)) if oe else (None, None)
    estimator = model.metadata.get("estimator", {})
    refine_cpu = sum(STAGES.cpu.get(s, 0.0) for s in REFINE_STAGES)
    refine_wall = sum(STAGES.wall.get(s, 0.0) for s in REFINE_STAGES)
    zmin, zmax = damping_ratios(n)
    return dict(
        n=n,
        terms=len(library),
        kg=kg,
        kc=kc,
        zeta=(zmin, zmax),
        cpu=cpu,
        wall=wall,
        ee_cpu=sum(STAGES.cpu.get(s, 0.0) for s in EE_STAGES),
        refine_cpu=refine_cpu,
        refine_wall=refine_wall,
        refine_seconds=info.get("seconds"),
        rounds=info.get("rounds"),
        fit=model.fit.value,
        stages=dict(STAGES.cpu),
        calls=dict(STAGES.calls),
        missing=missing,
        spurious=spurious,
        oe_missing=oe_missing,
        oe_spurious=oe_spurious,
        used=estimator.get("used", model.fit.value),
        doubts=len(estimator.get("doubts", [])),
        sizes=list(SIZES),
        sources=list(SOURCES),
        passes=list(PASSES),
        memory=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        model=str(model),
    )


def profile(n: int, folder: str, top: int = 15, measured: str = "all") -> None:
    system, record, naming, _ = observed(n, measured)
    library = symsbl.polynomial(list(system.states), 3) + symsbl.inputs(list(system.inputs))
    _empty_caches(folder)
    profiler = cProfile.Profile()
    with one_blas_thread():
        profiler.enable()
        identify(record, library, **naming)
        profiler.disable()
    stats = pstats.Stats(profiler, stream=io.StringIO()).stats
    total = max(v[3] for v in stats.values())
    for key, title in ((3, "cumulative"), (2, "own")):
        rows = []
        for (path, line, name), (_, calls, tottime, cumtime, _) in sorted(
            stats.items(), key=lambda kv: kv[1][key], reverse=True
        ):
            where = re.split(r"site-packages/|python3\.\d+/|wt-mdof/", path)[-1]
            label = f"{where}:{line}({name})"
            if "bench_mdof" in where and name == "timed_call":
                label = "the sensitivity pass's calls (Function.buffer: compiled C or CasADi's virtual machine)"
            elif "_lsprof" in name or "bench_mdof" in where or "_report" in where or "contextlib" in where:
                continue  # the profiler's own frames, this script's timers
            rows.append([label, calls, f"{cumtime:.1f}", f"{100 * cumtime / total:.0f} %",
                         f"{tottime:.1f}"])  # fmt: skip
            if len(rows) == top:
                break
        table(
            f"N = {n} under cProfile (empty caches, compiled again; {total:.1f} s in all): the {top} functions "
            f"with the most {title} time",
            ["function", "calls", "cumulative (s)", "cumulative share", "own (s)"],
            rows,
        )


def growth(ns, values) -> float:
    """Least-squares slope of log(values) against log(ns)."""
    return float(np.polyfit(np.log(ns), np.log(values), 1)[0])


def _share(r, stages) -> str:
    return f"{100 * sum(r['stages'].get(s, 0.0) for s in stages) / r['cpu']:.0f} %"


def _support(missing, spurious) -> str:
    if missing is None:
        return "-"
    wrong = [f"missing {', '.join(missing)}"] * bool(missing) + [f"spurious {', '.join(spurious)}"] * bool(spurious)
    return "; ".join(wrong) or "exact"


def report(results) -> None:
    table(
        "identify on an N-mass chain (CPU: the process and its children; shares of the CPU of identify)",
        ["N", "candidates", "CPU (s)", "wall (s)", "equation error (CPU s)", "refinement (CPU s)",
         "refinement (s, metadata)", "rounds", "compile", "sensitivity", "of which calls, compiled",
         "of which calls, VM", "rest", "peak memory (MB)"],
        [
            [r["n"], r["terms"], f"{r['cpu']:.1f}", f"{r['wall']:.1f}", f"{r['ee_cpu']:.1f}", f"{r['refine_cpu']:.1f}",
             "-" if r["refine_seconds"] is None else f"{r['refine_seconds']:.1f}", r["rounds"] or "-",
             _share(r, COMPILE), _share(r, SENSITIVITY), _share(r, ["sensitivity calls, compiled"]),
             _share(r, ["sensitivity calls, virtual machine"]),
             f"{100 - 100 * sum(r['stages'].get(s, 0.0) for s in (*COMPILE, *SENSITIVITY)) / r['cpu']:.0f} %",
             f"{r['memory']:.0f}"]
            for r in results
        ],
    )  # fmt: skip
    table(
        "Terms against the true equations: the model identify reports, and the output error's",
        ["N", "reported", "doubts", "missing", "spurious", "output error: missing", "output error: spurious"],
        [
            [r["n"], r["used"], r["doubts"], len(r["missing"]), len(r["spurious"]),
             "-" if r["oe_missing"] is None else len(r["oe_missing"]),
             "-" if r["oe_spurious"] is None else len(r["oe_spurious"])]
            for r in results
        ],
    )  # fmt: skip
    table(
        "Exclusive CPU seconds by stage (calls in brackets)",
        ["N", *EE_STAGES, *REFINE_STAGES],
        [
            [r["n"], *[f"{r['stages'].get(s, 0.0):.1f} ({r['calls'].get(s, 0)})" for s in (*EE_STAGES, *REFINE_STAGES)]]
            for r in results
        ],
    )  # fmt: skip
    table(
        "Generated C code (every compilation asked for) and the refinement's passes",
        ["N", "C sources", "total (kB)", "largest (kB)",
         "sensitivity passes (free coefficients, samples per call, C or VM)", "plain simulation passes"],
        [
            [r["n"], len(r["sources"]), f"{sum(b for _, b in r['sources']) / 1e3:.0f}",
             f"{max((b for _, b in r['sources']), default=0) / 1e3:.0f}",
             "; ".join(f"{p}, {c}, {'C' if ok else 'VM'}" for p, c, ok in r["sizes"]) or "-",
             ", ".join("C" if ok else "VM" for n, ok in r["passes"] if n.startswith("state_step")) or "-"]
            for r in results
        ],
    )  # fmt: skip
    if len(results) > 1:
        ns = [r["n"] for r in results]
        series = {
            "identify, CPU": [r["cpu"] for r in results],
            "identify, wall": [r["wall"] for r in results],
            "equation error, CPU": [r["ee_cpu"] for r in results],
            "refinement, CPU": [r["refine_cpu"] for r in results],
            "compile, CPU": [sum(r["stages"].get(s, 0.0) for s in COMPILE) for r in results],
            "sensitivity, CPU": [sum(r["stages"].get(s, 0.0) for s in SENSITIVITY) for r in results],
        }
        series = {k: np.maximum(v, 1e-3) for k, v in series.items()}
        rows = [
            [f"least squares over N = {', '.join(map(str, ns))}", *[f"{growth(ns, v):.2f}" for v in series.values()]]
        ]
        rows += [
            [f"N = {ns[i]} to {ns[i + 1]}", *[f"{growth(ns[i : i + 2], v[i : i + 2]):.2f}" for v in series.values()]]
            for i in range(len(ns) - 1)
        ]  # fmt: skip
        table("Growth exponent p of time ~ N^p", ["fitted on", *series], rows)
    for r in results:
        print(f"\nN = {r['n']}, reported ({r['used']}): {_support(r['missing'], r['spurious'])}")
        print(f"N = {r['n']}, output error: {_support(r['oe_missing'], r['oe_spurious'])}")
        print(r["model"])


def compiled(auto: dict, forced: dict) -> None:
    """The largest N with ``jit="auto"`` (the default) and with every pass of the refinement compiled."""
    rows = []
    for label, r in (("auto (default)", auto), ("True (every pass compiled)", forced)):
        rows.append([
            label, f"{r['cpu']:.1f}", f"{r['wall']:.1f}", f"{r['refine_cpu']:.1f}", _share(r, COMPILE),
            _share(r, SENSITIVITY), _share(r, ["sensitivity calls, compiled"]),
            _share(r, ["sensitivity calls, virtual machine"]),
            "; ".join(f"{p}, {c}, {'C' if ok else 'VM'}" for p, c, ok in r["sizes"]) or "-",
            _support(r["missing"], r["spurious"]), _support(r["oe_missing"], r["oe_spurious"]),
        ])  # fmt: skip
    table(
        f"N = {auto['n']} with the refinement's passes compiled whatever their size (RefineOptions jit=True)",
        ["jit", "CPU (s)", "wall (s)", "refinement (CPU s)", "compile", "sensitivity", "of which calls, compiled",
         "of which calls, VM", "sensitivity passes", "reported", "output error"],
        rows,
    )  # fmt: skip


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="2,3,5", help="comma-separated N")
    parser.add_argument("--big", action="store_true", help=f"also N = {MAX_N} (long: tens of minutes)")
    parser.add_argument(
        "--no-compiled", action="store_true", help="skip the largest N with the refinement's passes compiled"
    )
    parser.add_argument("--no-profile", action="store_true", help="skip the cProfile run of the largest N")
    parser.add_argument("--measured", choices=MEASURED, default="all", help="what the record holds (default: all)")
    args = parser.parse_args()
    sizes = sorted({int(s) for s in args.sizes.split(",")} | ({MAX_N} if args.big else set()))
    if min(sizes) < 2 or max(sizes) > MAX_N:
        parser.error(f"--sizes: N from 2 to {MAX_N}")
    _instrument()
    print(f"load average at start: {', '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)")
    results = []
    with tempfile.TemporaryDirectory(prefix="symsbl_bench_mdof_") as tmp:
        _empty_caches(os.path.join(tmp, "timed"))
        for n in sizes:
            r = run(n, measured=args.measured)
            results.append(r)
            print(
                f"N = {n}: {r['terms']} candidates, kg = {r['kg']:.3g}, kc = {r['kc']:.3g}, modal damping "
                f"{100 * r['zeta'][0]:.2f}-{100 * r['zeta'][1]:.2f} %: identify {r['cpu']:.1f} s CPU, "
                f"{r['wall']:.1f} s wall",
                flush=True,
            )
        report(results)
        if not args.no_compiled:
            _empty_caches(os.path.join(tmp, "compiled"))
            compiled(results[-1], run(max(sizes), jit=True, measured=args.measured))
        if not args.no_profile:
            profile(max(sizes), os.path.join(tmp, "profiled"), measured=args.measured)
    if args.measured == "all":
        write_page("mdof", __doc__)
    else:
        titled = __doc__.replace(" grows:", f" grows, recorded by its {args.measured} alone:", 1)
        write_page(f"mdof-{args.measured}", titled)


if __name__ == "__main__":
    main()
