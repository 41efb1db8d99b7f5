"""Classical fixed-step Runge-Kutta 4 (the paper's scheme), compiled: one SX step, ``mapaccum`` over chunks.

The step Function ``(x, t, dt, p[, ud]) -> x(t + dt)`` takes ``substeps`` RK4 steps over one sample
interval with the parameters ``p`` symbolic, so one compiled chunk serves every parameter value (Monte
Carlo draws, output-error iterations). Analytic inputs are evaluated at the stage times; sampled
inputs are held linear between samples (``u_k``, ``(u_k + u_{k+1}) / 2``, ``u_{k+1}`` at the stage
times). Chunks are JIT-compiled when a C compiler exists and written straight into numpy via
``Function.buffer()``; the state is carried from chunk to chunk.
"""

from __future__ import annotations

import hashlib

import casadi as ca
import numpy as np

from .._base.checks import integer
from .._base.errors import SimulationError
from .._base.jit import jit_lookup, jit_wrap
from .._base.progress import Progress
from .ode import OdeSystem
from .signals import Signal

__all__ = [
    "rk4_step",
    "chunk_function",
    "run_rk4",
    "run_rk4_batch",
    "step_inputs",
    "first_nonfinite_row",
    "JIT_MIN_STEPS",
]


def first_nonfinite_row(a: np.ndarray) -> int | None:
    """Index of the first row of ``a`` holding NaN/inf, or None (one summing pass in the common finite case)."""
    if np.isfinite(a.sum()):
        return None
    bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
    return int(bad[0]) if bad.size else None


#: ``jit="auto"`` compiles an RK4 chunk only for runs of at least this many RK4 steps, or once the runs of the same
#: structure and chunk length together reach it (or on a cache hit): compiling costs ~0.2-0.5 s, the SX virtual
#: machine ~0.5-1 us per step, the compiled chunk ~0.07-0.1 us.
JIT_MIN_STEPS = 2**18


def chunk_function(step: ca.Function, chunk: int, jit, n_work: int) -> ca.Function:
    """``mapaccum`` of ``step`` over ``chunk`` samples, JIT-compiled as a whole when it pays off.

    Compiling the per-step function alone does not help: ``mapaccum`` then calls it through the MX virtual
    machine, whose per-call overhead dominates. Compiling an MX wrapper around the mapaccum produces one C
    loop (source size independent of ``chunk``). Compiled chunks are cached per process by the serialised
    step graph and the chunk length.
    """
    acc = step.mapaccum("rk4_chunk", chunk)
    lazy = jit == "auto"  # compiled once this run, with the structure's earlier ones, reaches JIT_MIN_STEPS
    fn, _ = jit_wrap(
        acc, f"rk4_chunk_{chunk}", jit, SimulationError, only_cached=lazy, work=n_work, worth=JIT_MIN_STEPS
    )
    return fn


def rk4_step(system: OdeSystem, signals: list[Signal], substeps: int) -> tuple[ca.Function, int]:
    """SX Function ``(x, t, dt, p[, ud]) -> x(t + dt)``: ``substeps`` RK4 steps over one sample interval.

    The parameters ``p`` stay symbolic, so one compiled chunk serves every parameter value (e.g. Monte
    Carlo draws of an identified model). ``ud`` holds the sampled channels at the ``2 * substeps + 1``
    stage times (node-major).
    """
    pars = ca.vertcat(*system.parameters) if system.parameters else ca.SX(0, 1)
    rhs = ca.Function("rhs", [ca.vertcat(*system.states), ca.vertcat(*system.inputs), pars], [ca.vertcat(*system.rhs)])
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
                parts.append(ud[start : start + s.n_outputs])
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


def step_inputs(t, signals, substeps: int, n_ud: int, chunk: int) -> tuple[list[np.ndarray], int]:
    """Per-step times, steps and sampled inputs at the stage nodes, padded with ``dt = 0`` (a no-op step) up
    to a whole number of chunks; and the padded length."""
    n_steps = t.size - 1
    n_pad = -(-n_steps // chunk) * chunk
    tk = np.full(n_pad, t[-1])
    tk[:n_steps] = t[:-1]
    dt = np.zeros(n_pad)
    dt[:n_steps] = np.diff(t)
    args = [tk, dt]
    if n_ud:
        sampled = [s for s in signals if not s.is_analytic]
        ud = np.zeros((n_pad, n_ud))
        vals = np.stack([s.at_nodes(t, 2 * substeps + 1).reshape(-1, s.n_outputs) for s in sampled], 1)
        ud[:n_steps] = vals.reshape(n_steps, n_ud)
        args.append(ud)
    return args, n_pad


def run_rk4(system, t, signals, x0, *, rtol, atol, substeps, chunk_size, jit, options):
    """Fixed-step RK4 over ``t`` in chunks of ``chunk_size`` samples; stop at the first non-finite state."""
    substeps = integer("substeps", substeps, low=1, error=SimulationError)
    step, n_ud = rk4_step(system, signals, int(substeps))
    n_steps = t.size - 1
    chunk = max(1, min(int(chunk_size), n_steps))
    (tk, dt, *ud), n_pad = step_inputs(t, signals, int(substeps), n_ud, chunk)
    args = [tk, dt, np.tile(np.asarray(system.parameter_values, dtype=float), (n_pad, 1)), *ud]
    states = np.empty((n_pad + 1, system.n_states))
    states[0] = x0
    buf, trigger = chunk_function(step, chunk, jit, n_steps * int(substeps)).buffer()
    with Progress(f"simulate {system.name} (rk4)", total=n_steps, unit="steps") as bar:
        for k0 in range(0, n_pad, chunk):
            buf.set_arg(0, memoryview(states[k0]))
            for i, a in enumerate(args, start=1):
                buf.set_arg(i, memoryview(a[k0 : k0 + chunk]))
            block = states[k0 + 1 : k0 + chunk + 1]
            buf.set_res(0, memoryview(block))
            trigger()
            bad = first_nonfinite_row(block)
            if bad is not None and k0 + 1 + bad < t.size:
                row = k0 + 1 + bad
                states[row:] = np.nan
                return states[: t.size], float(t[row]), "the state became non-finite (NaN/inf)"
            bar.update(min(chunk, n_steps - k0))
    return states[: t.size], None, ""


def _batch_chunk(step: ca.Function, n_draws: int, chunk: int, jit, n_work: int) -> ca.Function:
    """``chunk`` RK4 steps of ``n_draws`` parameter vectors at once: ``(X (nx, D), t, dt, P (np, D)[, ud])``.

    The step is mapped over the draws (inputs of the original size, the time and the input, are shared),
    then accumulated over the chunk; the parameters enter once and are repeated inside the compiled code.
    """
    lazy = jit == "auto"  # compiled once this run, with the structure's earlier ones, reaches JIT_MIN_STEPS
    key = (hashlib.sha1(step.serialize().encode()).hexdigest(), "rk4_batch", n_draws, chunk)
    if jit is not False:
        cached = jit_lookup(key)
        if cached is not None:
            return cached
    shared = [1, 2] + ([4] if step.n_in() > 4 else [])  # time, step and input: the same for every draw
    mapped = step.map("rk4_draws", "serial", n_draws, shared, [])
    acc = mapped.mapaccum("rk4_batch_steps", chunk)
    args = [
        ca.MX.sym("x", step.size1_in(0), n_draws),
        ca.MX.sym("t", 1, chunk),
        ca.MX.sym("dt", 1, chunk),
        ca.MX.sym("p", step.size1_in(3), n_draws),
    ]
    call = args[:3] + [ca.repmat(args[3], 1, chunk)]
    if step.n_in() > 4:
        args.append(ca.MX.sym("ud", step.size1_in(4), chunk))
        call.append(args[4])
    wrapper = ca.Function("rk4_batch", args, [acc(*call)], ["x", "t", "dt", "p", "ud"][: len(args)], ["x_next"])
    fn, _ = jit_wrap(
        wrapper, "rk4_batch", jit, SimulationError, only_cached=lazy, key=key, work=n_work, worth=JIT_MIN_STEPS
    )
    return fn


def run_rk4_batch(
    system: OdeSystem, t, signals, x0, parameters, *, substeps: int = 1, chunk_size: int = 4096, jit="auto"
) -> tuple[np.ndarray, np.ndarray]:
    """RK4 of ``system`` for every row of ``parameters`` in one compiled call per chunk.

    Parameters
    ----------
    system : OdeSystem
    t : ndarray, shape (n_samples,)
    signals : list of Signal
    x0 : ndarray, shape (n_states,)
        The initial state, shared by every draw.
    parameters : ndarray, shape (n_draws, n_parameters)

    Returns
    -------
    states : ndarray, shape (n_samples, n_draws, n_states)
    finite : ndarray of bool, shape (n_draws,)
        Whether each draw's simulation stayed finite (a diverged draw holds NaN/inf from where it blew up).
    """
    P = np.ascontiguousarray(np.atleast_2d(parameters), dtype=float)
    D = P.shape[0]
    step, n_ud = rk4_step(system, signals, int(substeps))
    n_steps = t.size - 1
    chunk = max(1, min(int(chunk_size) // max(1, D // 8), n_steps))
    inputs, n_pad = step_inputs(t, signals, int(substeps), n_ud, chunk)
    fn = _batch_chunk(step, D, chunk, jit, n_steps * int(substeps) * D)
    buf, trigger = fn.buffer()
    states = np.empty((n_pad + 1, D, system.n_states))
    states[0] = x0
    # CasADi's column-major (np, D) is the C-ordered (D, np)
    buf.set_arg(3, memoryview(P))  # type: ignore[call-arg, arg-type]
    with Progress(f"simulate {system.name} x {D} draws (rk4)", total=n_steps, unit="steps") as bar:
        for k0 in range(0, n_pad, chunk):
            buf.set_arg(0, memoryview(states[k0]))  # type: ignore[call-arg]
            buf.set_arg(1, memoryview(inputs[0][k0 : k0 + chunk]))  # type: ignore[call-arg, arg-type]
            buf.set_arg(2, memoryview(inputs[1][k0 : k0 + chunk]))  # type: ignore[call-arg, arg-type]
            if n_ud:
                buf.set_arg(4, memoryview(inputs[2][k0 : k0 + chunk]))  # type: ignore[call-arg, arg-type]
            buf.set_res(0, memoryview(states[k0 + 1 : k0 + chunk + 1]))  # type: ignore[call-arg, arg-type]
            trigger()
            bar.update(min(chunk, n_steps - k0))
    out = states[: t.size]
    return out, np.isfinite(out).all(axis=(0, 2))  # type: ignore[return-value]
