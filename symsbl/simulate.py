"""Simulate an :class:`~symsbl.system.OdeSystem` on an output grid with a CasADi integrator.

Two integrators, one registry (:data:`METHODS`):

* ``"cvodes"``: SUNDIALS CVODES (BDF, error-controlled), through ``ca.integrator(name, "cvodes", dae, t0, t)``.
  Analytic inputs enter as expressions of the time symbol (``dae["t"] + t_offset``), sampled inputs as a
  linear ``ca.interpolant`` of time, so the solver sees the input between samples exactly. Long grids are
  integrated in segments of :data:`CVODES_SEGMENT` samples (the state carried across, ``t_offset`` the
  segment's start), so that a long run can report its progress.
* ``"rk4"``: classical fixed-step Runge-Kutta 4 (the paper's scheme) with ``substeps`` steps per sample,
  built as one SX step Function, repeated with ``mapaccum`` over chunks of samples (the state carried from
  chunk to chunk), JIT-compiled when a C compiler exists and written straight into numpy via
  ``Function.buffer()``. Analytic inputs are evaluated at the stage times; sampled inputs are held linear
  between samples (``u_k``, ``(u_k + u_{k+1}) / 2``, ``u_{k+1}`` at the stage times).

``"auto"`` takes cvodes for continuous right-hand sides and RK4 for discontinuous ones (see :func:`simulate`).
"""

from __future__ import annotations

import atexit
import hashlib
import shutil
import tempfile
from collections import OrderedDict
from typing import Sequence

import casadi as ca
import numpy as np

from symsbl.data import Trajectory, validate
from symsbl.errors import SimulationError
from symsbl.progress import Progress
from symsbl.signals import FreeDecay, Sampled, Signal
from symsbl.system import OdeSystem

__all__ = ["simulate", "time_grid", "METHODS"]

_JIT_CACHE: OrderedDict[tuple, ca.Function] = OrderedDict()
_JIT_CACHE_SIZE = 32
_JIT_DIR: str | None = None


def time_grid(duration: float, fs: float, t0: float = 0.0) -> np.ndarray:
    """Uniform grid ``t0 + arange(round(duration * fs) + 1) / fs`` (both ends included), shape ``(n_samples,)``.

    Examples
    --------
    >>> import symsbl
    >>> symsbl.time_grid(1.0, 4)
    array([0.  , 0.25, 0.5 , 0.75, 1.  ])
    """
    n = int(round(duration * fs))
    if n < 1:
        raise SimulationError(f"duration * fs must be >= 1 sample interval; received {duration} s at {fs} Hz.")
    return t0 + np.arange(n + 1) / float(fs)


# ------------------------------------------------------------------------------------------- inputs


def _resolve_inputs(system: OdeSystem, t: np.ndarray, inputs) -> list[Signal]:
    """Turn ``inputs`` (None, a Signal, a sequence of Signals or an array on ``t``) into a list of Signals."""
    if inputs is None:
        signals = [FreeDecay(system.n_inputs)] if system.n_inputs else []
    elif isinstance(inputs, Signal):
        signals = [inputs]
    elif isinstance(inputs, np.ndarray) or (
        isinstance(inputs, Sequence) and inputs and not isinstance(inputs[0], Signal)
    ):
        arr = np.asarray(inputs, dtype=float)
        if arr.shape[0] != t.size:
            raise SimulationError(
                f"an inputs array must be sampled on t: shape ({t.size},) or ({t.size}, {system.n_inputs}); "
                f"received {arr.shape}."
            )
        signals = [Sampled(t, arr)]
    else:
        signals = list(inputs)
        for s in signals:
            if not isinstance(s, Signal):
                raise SimulationError(f"inputs must be Signals or an array; received an element {s!r}.")
    n = sum(s.n_outputs for s in signals)
    if n != system.n_inputs:
        raise SimulationError(
            f"{system.name!r} has {system.n_inputs} input(s) {list(system.input_names)} but the signals give {n}; "
            "pass one signal per input (FreeDecay() for a zero input)."
        )
    for s in signals:
        if isinstance(s, Sampled) and (t[0] < s.t[0] - 1e-9 * np.ptp(s.t) or t[-1] > s.t[-1] + 1e-9 * np.ptp(s.t)):
            raise SimulationError(
                f"the simulation grid [{t[0]}, {t[-1]}] leaves the span of a sampled input "
                f"[{s.t[0]}, {s.t[-1]}]; shorten t or supply samples covering it."
            )
    return signals


def _first_nonfinite_row(a: np.ndarray) -> int | None:
    """Index of the first row of ``a`` holding NaN/inf, or None (one summing pass in the common finite case)."""
    if np.isfinite(a.sum()):
        return None
    bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
    return int(bad[0]) if bad.size else None


def _input_samples(signals: list[Signal], t: np.ndarray) -> np.ndarray:
    cols = [np.asarray(s(t), dtype=float).reshape(t.size, s.n_outputs) for s in signals]
    return np.hstack(cols) if cols else np.empty((t.size, 0))


# ------------------------------------------------------------------------------------------- cvodes


#: CVODES integrates long grids in segments of this many sample intervals (the state carried
#: across), so that a long run reports its progress; each segment restarts the solver, which
#: costs a few small steps (measured on Duffing at 32768 Hz: +1 % run time, changes below rtol).
CVODES_SEGMENT = 2**16


def _cvodes(system, t, signals, x0, *, rtol, atol, substeps, chunk_size, jit, options):
    """Integrate with CVODES; return ``(states (n, nx) with NaN after a failure, failure time or None, reason)``."""
    x = ca.vertcat(*system.states)
    ts, offset = ca.SX.sym("t"), ca.SX.sym("t_offset")
    u = ca.vertcat(*[s.expr(ts + offset) for s in signals]) if signals else ca.SX(0, 1)
    ode = system.rhs_function()(x, u)
    opts = {"reltol": rtol, "abstol": atol, "disable_internal_warnings": True}
    opts.update(options or {})
    dae = {"x": x, "p": offset, "t": ts, "ode": ode}
    out = np.full((t.size, system.n_states), np.nan)
    out[0] = x0
    # The integrator of the previous segment is reused when its relative output grid is this
    # segment's: a uniform grid builds one (two with a shorter last segment), a measured grid
    # with jitter one per segment.
    solver = None
    tol = 1e-9 * float(np.min(np.diff(t)))
    with Progress(f"simulate {system.name} (cvodes)", total=t.size - 1, unit="steps") as bar:
        for a in range(0, t.size - 1, CVODES_SEGMENT):
            b = min(a + CVODES_SEGMENT, t.size - 1)
            grid = t[a + 1:b + 1] - t[a]
            if solver is None or solver[0].size != grid.size or not np.allclose(solver[0], grid, rtol=0, atol=tol):
                try:
                    F = ca.integrator("simulate", "cvodes", dae, 0.0, grid, opts)
                except RuntimeError as err:
                    raise SimulationError(f"could not build the cvodes integrator: {err}") from None
                solver = (grid, *F.buffer(), F.index_in("p"))
            _, buf, trigger, i_p = solver
            start, shift = np.array(out[a]), np.array([t[a]])
            buf.set_arg(0, memoryview(start))
            buf.set_arg(i_p, memoryview(shift))
            buf.set_res(0, memoryview(out[a + 1:b + 1]))
            try:
                trigger()
            except RuntimeError as err:
                reason = str(err).strip().splitlines()[-1].split(": ", 1)[-1]
                done = np.flatnonzero(np.all(np.isfinite(out), axis=1))
                t_last = t[done[-1]] if done.size else t[0]
                t_fail = buf.stats().get("tcur", np.nan)  # where CVODES stopped (segment time), if it says
                t_fail = float(t_fail) + t[a] if np.isfinite(t_fail) else -np.inf
                return out, (t_fail if t_fail > t_last else float(t_last)), f"cvodes failed: {reason}"
            bar.update(b - a)
    return out, None, ""


# ------------------------------------------------------------------------------------------- RK4


def _jit_dir() -> str:
    global _JIT_DIR
    if _JIT_DIR is None:
        _JIT_DIR = tempfile.mkdtemp(prefix="symsbl_jit_")
        atexit.register(shutil.rmtree, _JIT_DIR, True)
    return _JIT_DIR + "/"


#: ``jit="auto"`` compiles an RK4 chunk only for runs of at least this many RK4 steps (or on a cache hit):
#: compiling costs ~0.5 s, the SX virtual machine ~0.5-1 us per step, the compiled chunk ~0.07-0.1 us.
JIT_MIN_STEPS = 2**18


def _chunk_function(step: ca.Function, chunk: int, jit, n_work: int) -> ca.Function:
    """``mapaccum`` of ``step`` over ``chunk`` samples, JIT-compiled as a whole when it pays off.

    Compiling the per-step function alone does not help: ``mapaccum`` then calls it through the MX virtual
    machine, whose per-call overhead dominates. Compiling an MX wrapper around the mapaccum produces one C
    loop (source size independent of ``chunk``). Compiled chunks are cached per process by the serialised
    step graph and the chunk length.
    """
    if jit is not False:
        key = (hashlib.sha1(step.serialize().encode()).hexdigest(), chunk)
        if key in _JIT_CACHE:
            _JIT_CACHE.move_to_end(key)
            return _JIT_CACHE[key]
    acc = step.mapaccum("rk4_chunk", chunk)
    if jit is False:
        return acc
    if not (shutil.which("gcc") or shutil.which("cc")):
        if jit is True:
            raise SimulationError("jit=True needs a C compiler (gcc or cc) on PATH; install one or use jit='auto'.")
        return acc
    if jit == "auto" and n_work < JIT_MIN_STEPS:
        return acc
    args = [ca.MX.sym(acc.name_in(i), acc.sparsity_in(i)) for i in range(acc.n_in())]
    opts = {"jit": True, "compiler": "shell", "jit_cleanup": False,
            "jit_options": {"directory": _jit_dir(), "flags": ["-O3", "-march=native"], "cleanup": False}}
    try:
        compiled = ca.Function("rk4_chunk", args, [acc(*args)], acc.name_in(), acc.name_out(), opts)
    except RuntimeError as err:
        if jit is True:
            raise SimulationError(f"JIT compilation of the RK4 chunk failed: {err}") from None
        return acc
    _JIT_CACHE[key] = compiled
    if len(_JIT_CACHE) > _JIT_CACHE_SIZE:
        _JIT_CACHE.popitem(last=False)
    return compiled


def _rk4_step(system: OdeSystem, signals: list[Signal], substeps: int) -> tuple[ca.Function, int]:
    """SX Function ``(x, t, dt, p[, ud]) -> x(t + dt)``: ``substeps`` RK4 steps over one sample interval.

    The parameters ``p`` stay symbolic, so one compiled chunk serves every parameter value (e.g. Monte
    Carlo draws of an identified model). ``ud`` holds the sampled channels at the ``2 * substeps + 1``
    stage times (node-major).
    """
    pars = ca.vertcat(*system.parameters) if system.parameters else ca.SX(0, 1)
    rhs = ca.Function("rhs", [ca.vertcat(*system.states), ca.vertcat(*system.inputs), pars],
                      [ca.vertcat(*system.rhs)])
    p = ca.SX.sym("p", pars.numel())
    x = ca.SX.sym("x", system.n_states)
    tk, dt = ca.SX.sym("t"), ca.SX.sym("dt")
    n_sampled = sum(s.n_outputs for s in signals if not s.is_analytic)
    n_nodes = 2 * substeps + 1
    ud = ca.SX.sym("ud", n_sampled * n_nodes)

    def u_at(node: int):
        parts, col = [], 0
        for s in signals:
            if s.is_analytic:
                parts.append(s.expr(tk + node * dt / (2 * substeps)))
            else:
                start = node * n_sampled + col
                parts.append(ud[start:start + s.n_outputs])
                col += s.n_outputs
        return ca.vertcat(*parts) if parts else ca.SX(0, 1)

    def f(xs, us):
        return rhs(xs, us, p)

    h = dt / substeps
    xi = x
    for j in range(substeps):
        k1 = f(xi, u_at(2 * j))
        k2 = f(xi + h / 2 * k1, u_at(2 * j + 1))
        k3 = f(xi + h / 2 * k2, u_at(2 * j + 1))
        k4 = f(xi + h * k3, u_at(2 * j + 2))
        xi = xi + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    args, names = [x, tk, dt, p], ["x", "t", "dt", "p"]
    if n_sampled:
        args.append(ud)
        names.append("ud")
    return ca.Function("rk4_step", args, [xi], names, ["x_next"]), n_sampled * n_nodes


def _rk4(system, t, signals, x0, *, rtol, atol, substeps, chunk_size, jit, options):
    """Fixed-step RK4 over ``t`` in chunks of ``chunk_size`` samples; stop at the first non-finite state."""
    if not (isinstance(substeps, (int, np.integer)) and substeps >= 1):
        raise SimulationError(f"substeps must be a positive integer; received {substeps!r}.")
    step, n_ud = _rk4_step(system, signals, int(substeps))
    n_steps = t.size - 1
    chunk = max(1, min(int(chunk_size), n_steps))
    n_pad = -(-n_steps // chunk) * chunk
    # Per-step inputs, padded with dt = 0 (a no-op step) up to a whole number of chunks.
    tk = np.full(n_pad, t[-1])
    tk[:n_steps] = t[:-1]
    dt = np.zeros(n_pad)
    dt[:n_steps] = np.diff(t)
    args = [tk, dt, np.tile(np.asarray(system.parameter_values, dtype=float), (n_pad, 1))]
    if n_ud:
        nodes = t[:-1, None] + np.diff(t)[:, None] * np.arange(2 * substeps + 1) / (2 * substeps)
        sampled = [s for s in signals if not s.is_analytic]
        ud = np.zeros((n_pad, n_ud))
        vals = np.stack([np.asarray(s(nodes.ravel())).reshape(nodes.size, s.n_outputs) for s in sampled], 1)
        ud[:n_steps] = vals.reshape(n_steps, n_ud)
        args.append(ud)
    states = np.empty((n_pad + 1, system.n_states))
    states[0] = x0
    buf, trigger = _chunk_function(step, chunk, jit, n_steps * int(substeps)).buffer()
    with Progress(f"simulate {system.name} (rk4)", total=n_steps, unit="steps") as bar:
        for k0 in range(0, n_pad, chunk):
            buf.set_arg(0, memoryview(states[k0]))
            for i, a in enumerate(args, start=1):
                buf.set_arg(i, memoryview(a[k0:k0 + chunk]))
            block = states[k0 + 1:k0 + chunk + 1]
            buf.set_res(0, memoryview(block))
            trigger()
            bad = _first_nonfinite_row(block)
            if bad is not None and k0 + 1 + bad < t.size:
                row = k0 + 1 + bad
                states[row:] = np.nan
                return states[:t.size], float(t[row]), "the state became non-finite (NaN/inf)"
            bar.update(min(chunk, n_steps - k0))
    return states[:t.size], None, ""


METHODS = {"cvodes": _cvodes, "rk4": _rk4}
_DIVERGENCE = ("raise", "truncate", "return")
_JIT = ("auto", True, False)  # listed in the error message


def simulate(
    system: OdeSystem,
    t,
    *,
    inputs=None,
    x0=None,
    method: str = "auto",
    rtol: float = 1e-10,
    atol: float = 1e-12,
    substeps: int = 1,
    on_divergence: str = "raise",
    chunk_size: int = 4096,
    jit="auto",
    options: dict | None = None,
) -> Trajectory:
    """Simulate ``system`` from ``x0`` and return its states and inputs on the grid ``t``.

    Parameters
    ----------
    system : OdeSystem
    t : array_like, shape (n_samples,)
        Uniform, strictly increasing output grid; the first entry is the initial time
        (:func:`time_grid` builds one).
    inputs : Signal, sequence of Signal, array_like or None
        One signal per input channel (a multi-channel :class:`~symsbl.signals.Sampled` covers several), an
        array sampled on ``t`` of shape ``(n_samples,)`` or ``(n_samples, n_inputs)`` (linearly interpolated),
        or None for free decay (all inputs zero).
    x0 : array_like, shape (n_states,), optional
        Initial state; zeros by default.
    method : {"auto", "cvodes", "rk4"}
        ``"auto"`` uses cvodes when ``system.is_continuous`` and RK4 otherwise (see Notes).
    rtol, atol : float
        CVODES relative and absolute tolerances (cvodes only).
    substeps : int
        RK4 steps per sample interval (RK4 only). 1 reproduces the paper's scheme.
    on_divergence : {"raise", "truncate"}
        What to do when the state becomes NaN/inf or the integrator fails. ``"raise"``: raise
        :class:`SimulationError` naming the time. ``"truncate"`` (alias ``"return"``): return the trajectory
        up to the last good sample; the caller learns the failure time from ``traj.diverged_at`` (``None``
        when the simulation completed). Fewer than 2 good samples always raises.
    chunk_size : int
        RK4 samples per ``mapaccum`` call (bounded build memory; the state is carried between chunks).
    jit : {"auto", True, False}
        Compile each RK4 chunk (``mapaccum`` of the step) to C with the system compiler (about 0.5 s, then
        ~0.1 us per step against ~0.5-1 us in CasADi's virtual machine). ``"auto"``: compile when a compiler
        exists and the run has at least :data:`JIT_MIN_STEPS` RK4 steps, or a compiled chunk is already
        cached; silently fall back to the virtual machine if compilation fails. ``True`` always compiles
        (raising if it cannot). Compiled chunks are cached per process; parameter values are inputs of the
        compiled code, so ``system.with_parameters(...)`` reuses it.
    options : dict, optional
        Extra ``ca.integrator`` options for cvodes (e.g. ``{"linear_multistep_method": "adams"}``).

    Returns
    -------
    Trajectory
        ``states`` on every ``t``, ``inputs`` (the signals sampled on ``t``), the system's names, and
        ``diverged_at``.

    Raises
    ------
    SimulationError
        Bad arguments (unknown method, wrong number of signals, ``x0`` shape), or divergence with
        ``on_divergence="raise"``.

    Notes
    -----
    **Discontinuous right-hand sides.** Adaptive solvers (CVODES, and scipy's RK45/DOP853/LSODA/BDF) stall
    on ``sign(x2)``: once the velocity reaches 0 they chatter around the switch, shrinking the step until the
    step budget is spent (CVODES stops with ``CV_TOO_MUCH_WORK`` at t ~ 3e-9 s on the Coulomb system; that
    is reported as a divergence). ``method="auto"`` therefore integrates any system whose right-hand side
    can jump (sign, conditionals, comparisons, floor/ceil: ``system.is_continuous`` is False) with
    fixed-step RK4, which cannot stall. Kinks (abs, min, max, as in Bouc-Wen) do not stall CVODES, which
    then stays far more accurate than RK4 (Bouc-Wen n=3, 32768 Hz: 5e-8 against 1.6e-5 for RK4 with one
    step per sample), so "auto" keeps cvodes for them.

    RK4 loses its 4th order at the switches: the step that crosses ``x2 = 0`` commits an O(h**2) local
    error, so the global error is first order in the step. Measured on ``coulomb()`` (kc = 1) driven by
    ``Sine(100, 10)`` for 1 s at 32768 Hz, against RK4 with 64 substeps: max error in x1 relative to its
    peak of 9.8e-6 with 1 substep, 6.1e-6 with 2, 2.7e-6 with 4, 1.3e-6 with 8 (observed order 0.7-1.2);
    with kc = 30 (a longer stick phase) 5.2e-4 with 1 substep and 1.6e-4 with 2. Raise ``substeps`` when
    this matters; the smooth parts of the trajectory keep RK4's 4th-order accuracy.

    Examples
    --------
    Exponential decay ``x' = -2 x`` from ``x(0) = 1`` against its closed form ``exp(-2 t)``:

    >>> import numpy as np
    >>> import symsbl
    >>> (x,) = symsbl.symbols("x")
    >>> decay = symsbl.OdeSystem((x,), (), (-2 * x,), name="decay")
    >>> traj = symsbl.simulate(decay, symsbl.time_grid(1.0, 100), x0=[1.0])
    >>> traj.states.shape
    (101, 1)
    >>> bool(abs(traj.states[-1, 0] - np.exp(-2.0)) < 1e-8)
    True

    The paper's Duffing oscillator under its 100 N, 10 Hz sine:

    >>> duffing = symsbl.systems.duffing()
    >>> symsbl.simulate(duffing, symsbl.time_grid(0.5, 8192), inputs=symsbl.Sine(100.0, 10.0))
    Trajectory(4097 samples, 0 to 0.5 s at 8192 Hz, states=['x1', 'x2'], inputs=['F'])
    """
    if method != "auto" and method not in METHODS:
        raise SimulationError(f"method must be one of {['auto', *METHODS]}; received {method!r}.")
    if on_divergence not in _DIVERGENCE:
        raise SimulationError(f"on_divergence must be one of {list(_DIVERGENCE[:2])}; received {on_divergence!r}.")
    if not (jit is True or jit is False or (isinstance(jit, str) and jit == "auto")):
        raise SimulationError(f"jit must be one of {list(_JIT)}; received {jit!r}.")
    if not isinstance(system, OdeSystem):
        raise SimulationError(f"system must be an OdeSystem; received {type(system).__name__}.")
    t, _, _ = validate(t, np.empty((np.size(t), 0)))
    x0 = np.zeros(system.n_states) if x0 is None else np.array(x0, dtype=float).ravel()
    if x0.shape != (system.n_states,) or not np.all(np.isfinite(x0)):
        raise SimulationError(
            f"x0 must be {system.n_states} finite values (states {list(system.state_names)}); received {x0!r}."
        )
    signals = _resolve_inputs(system, t, inputs)
    name = method if method != "auto" else ("cvodes" if system.is_continuous else "rk4")
    states, t_fail, reason = METHODS[name](
        system, t, signals, x0, rtol=rtol, atol=atol, substeps=substeps, chunk_size=chunk_size, jit=jit,
        options=options,
    )
    U = _input_samples(signals, t)
    bad = _first_nonfinite_row(states)
    if t_fail is None and bad is not None:
        t_fail, reason = float(t[bad]), reason or "the state became non-finite (NaN/inf)"
    if t_fail is None:
        return Trajectory(t, states, U, system.state_names, system.input_names)
    n_good = t.size if bad is None else bad
    if on_divergence == "raise" or n_good < 2:
        hint = (" Pass on_divergence='truncate' to get the trajectory up to that point." if n_good >= 2
                else " Fewer than 2 samples were computed, so there is nothing to return.")
        if name == "cvodes" and not system.is_continuous:
            hint += " The right-hand side is discontinuous: use method='rk4' (or 'auto')."
        raise SimulationError(
            f"simulation of {system.name!r} with {name} diverged at t = {t_fail:.6g} s ({reason})." + hint
        )
    return Trajectory(t[:n_good], states[:n_good], U[:n_good], system.state_names, system.input_names,
                      diverged_at=t_fail)
