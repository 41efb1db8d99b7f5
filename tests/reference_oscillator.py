"""Records of a hardening oscillator with known truth, simulated independently of symsbl.

``m x'' + c x' + k x + k3 x^3 + Fc sign(x') = F + w(t)``, integrated by scipy's DOP853 (rtol 1e-10) on an analytic
input (a sum of sinusoids, so the integrator sees the exact force between samples), with velocity reversals
located as events when there is Coulomb friction (the mass sticks while the net force cannot overcome Fc). A
closed loop is integrated by classical RK4 at 16 substeps per sample with the controller's output held over each
sample, the way a digital controller drives a plant.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq
from scipy.signal import lfilter

import symsbl


@dataclasses.dataclass(frozen=True)
class Plant:
    """The oscillator's physical parameters."""

    m: float
    c: float
    k: float
    k3: float
    fc: float = 0.0

    def truth(self) -> dict:
        """The true coefficients of ``v'`` in symsbl's term names."""
        out = {"F": 1 / self.m, "x": -self.k / self.m, "v": -self.c / self.m, "x**3": -self.k3 / self.m}
        if self.fc:
            out["sign(v)"] = -self.fc / self.m
        return out

    def acceleration(self, x, v, force, sign=None):
        friction = self.fc * (np.sign(v) if sign is None else sign)
        return (force - self.c * v - self.k * x - self.k3 * x**3 - friction) / self.m


HARDENING = Plant(m=0.7, c=1.1, k=3e3, k3=4e7)
COULOMB = Plant(m=1.0, c=0.8, k=400.0, k3=2e5, fc=0.6)


@dataclasses.dataclass(frozen=True)
class SumOfSines:
    """``sum_i a_i cos(2 pi f_i t + phi_i)``."""

    f: np.ndarray
    a: np.ndarray
    phi: np.ndarray

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        return np.sum(
            self.a[:, None] * np.cos(2 * np.pi * self.f[:, None] * t.ravel() + self.phi[:, None]), axis=0
        ).reshape(t.shape)

    def scalar(self, t: float) -> float:
        return float(np.sum(self.a * np.cos(2 * np.pi * self.f * t + self.phi)))


def multisine(rms, f_min, f_max, period, rng) -> SumOfSines:
    """A random-phase multisine: flat amplitudes on the lines ``k / period`` in ``[f_min, f_max]``."""
    f = np.arange(np.ceil(f_min * period), np.floor(f_max * period) + 1) / period
    return SumOfSines(f, np.full(f.size, rms * np.sqrt(2.0 / f.size)), rng.uniform(0, 2 * np.pi, f.size))


def random_force(rms, f_min, f_max, rng, n=400) -> SumOfSines:
    """A band-limited, nearly Gaussian random force: ``n`` sinusoids at random frequencies off the input's lines."""
    f = rng.uniform(f_min, f_max, n)
    a = rng.rayleigh(1.0, n)
    return SumOfSines(f, a * rms / np.sqrt(np.sum(a**2) / 2), rng.uniform(0, 2 * np.pi, n))


def simulate(plant: Plant, force, t, disturbance=None) -> np.ndarray:
    """States ``(x, v)`` on the grid ``t`` from rest."""

    def total(tt):
        return force.scalar(tt) + (disturbance.scalar(tt) if disturbance is not None else 0.0)

    def rhs(tt, s, sign):
        return [s[1], plant.acceleration(s[0], s[1], total(tt), sign)]

    opts = dict(method="DOP853", rtol=1e-10, atol=1e-13, max_step=t[1] - t[0])
    if plant.fc == 0.0:
        sol = solve_ivp(rhs, (t[0], t[-1]), [0.0, 0.0], t_eval=t, args=(None,), **opts)
        return sol.y.T
    out = np.empty((t.size, 2))
    t0, s0 = t[0], np.zeros(2)
    t0, sign, i = _stick(plant, total, t, t0, s0, out, 0)
    while i < t.size:

        def reversal(tt, s, sg):
            return s[1]

        reversal.terminal, reversal.direction = True, -sign
        sol = solve_ivp(rhs, (t0, t[-1]), list(s0), t_eval=t[i:], events=reversal, args=(sign,), **opts)
        out[i : i + sol.y.shape[1]] = sol.y.T
        i += sol.y.shape[1]
        if sol.status == 0 or i >= t.size:
            break
        t0, s0 = sol.t_events[0][0], np.array([sol.y_events[0][0][0], 0.0])
        t0, sign, i = _stick(plant, total, t, t0, s0, out, i)
    return out


def _stick(plant, total, t, t0, s0, out, i):
    """At ``v = 0`` the mass sticks until the net force exceeds Fc; its samples are written into ``out``. The release
    time, the new sliding direction and the next sample."""
    x = s0[0]

    def net(tt):
        return total(tt) - plant.k * x - plant.k3 * x**3

    if abs(net(t0)) > plant.fc:
        return t0, float(np.sign(net(t0))), i
    h, ta = (t[1] - t[0]) / 64, t0
    release = t[-1] + 1.0
    while ta + h <= t[-1]:
        if abs(net(ta + h)) > plant.fc:
            release = brentq(lambda tt: abs(net(tt)) - plant.fc, ta, ta + h, xtol=1e-15)
            break
        ta += h
    while i < t.size and t[i] <= release:
        out[i] = (x, 0.0)
        i += 1
    return release, float(np.sign(net(release + 1e-12))), i


#: ``A(q)`` of a low-pass AR(2) measurement noise with a double pole at r: ``((1 + r) / (1 - r))^4`` = 20 dB
#: between its spectrum's maximum and minimum.
AR2 = (lambda r: np.array([1.0, -2 * r, r * r]))((10**0.5 - 1) / (10**0.5 + 1))


def record(
    plant: Plant,
    seed: int,
    *,
    fs=1000.0,
    seconds=4.0,
    rms=4.0,
    band=(2.0, 30.0),
    noise=0.01,
    force_noise=0.0,
    process=0.0,
    coloured=False,
) -> symsbl.Trajectory:
    """A measured record: noise of ``noise`` times each state's spread on ``x`` and ``v`` (white, or ``coloured``
    by :data:`AR2`), ``force_noise`` on the recorded force, and a random force of ``process`` times the input's rms
    that the record does not hold."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(seconds * fs)) + 1) / fs
    force = multisine(rms, band[0], band[1], seconds, rng)
    hidden = random_force(process * rms, 1.0, 50.0, rng) if process else None
    clean = simulate(plant, force, t, hidden)
    w = rng.standard_normal((clean.shape[0] + 2000, 2))
    e = lfilter([1.0], AR2, w, axis=0)[2000:] if coloured else w[2000:]
    states = clean + noise * clean.std(axis=0) * e / e.std(axis=0)
    f = force(t)
    f = f + force_noise * f.std() * rng.standard_normal(f.size)
    return symsbl.Trajectory(t, states, f[:, None], ("x", "v"), ("F",))


def closed_loop(
    plant: Plant, seed: int, *, fs=1000.0, seconds=4.0, rms=4.0, gains=(2e3, 20.0), noise=0.01, process=0.05
) -> symsbl.Trajectory:
    """A record under a digital PD controller ``F_i = r_i - kp x_{i-1} - kd v_{i-1}`` on the previous sample's
    measurements, held over each sample: the input depends on the response to a random disturbance force the
    record does not hold (white over each sample, ``process`` times the reference's rms)."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * fs)) + 1
    t = np.arange(n) / fs
    reference = multisine(rms, 2.0, 30.0, seconds, rng)(t)
    hidden = process * rms * rng.standard_normal(n)
    scale = np.array([2e-3, 0.1])  # the states' spread, for the noise level before the run
    s, y, states, forces, substeps = np.zeros(2), np.zeros(2), np.empty((n, 2)), np.empty(n), 16
    for i in range(n):
        forces[i] = reference[i] - gains[0] * y[0] - gains[1] * y[1]
        y = s + noise * scale * rng.standard_normal(2)
        states[i] = y
        total, h = forces[i] + hidden[i], 1.0 / (fs * substeps)
        for _ in range(substeps):
            s = _rk4(plant, s, total, h)
    return symsbl.Trajectory(t, states, forces[:, None], ("x", "v"), ("F",))


def _rk4(plant: Plant, s, force, h):
    def f(z):
        return np.array([z[1], plant.acceleration(z[0], z[1], force)])

    k1 = f(s)
    k2 = f(s + h / 2 * k1)
    k3 = f(s + h / 2 * k2)
    k4 = f(s + h * k3)
    return s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def library() -> symsbl.Library:
    """Polynomials of degree 3 in ``x, v`` with absolute values, ``sin`` and ``sign`` of each, and the force."""
    x, v, F = symsbl.symbols("x v F")
    return (
        symsbl.polynomial([x, v], 3, absolute=True) + symsbl.elementwise([x, v], ["sin", "sign"]) + symsbl.inputs([F])
    )


def accelerations(plant: Plant, states: np.ndarray, force: np.ndarray) -> np.ndarray:
    """The mass's acceleration at every sample of clean ``states`` ``(n, 2)`` under ``force`` ``(n,)`` (a stuck
    mass, ``v = 0`` with the net force inside the friction, does not accelerate)."""
    x, v = states[:, 0], states[:, 1]
    a = plant.acceleration(x, v, force)
    if plant.fc:
        net = force - plant.k * x - plant.k3 * x**3
        stuck = (v == 0.0) & (np.abs(net) <= plant.fc)
        a = np.where(stuck, 0.0, np.where(v == 0.0, (net - plant.fc * np.sign(net)) / plant.m, a))
    return a


def accelerometer_record(
    plant: Plant, seed: int, *, fs=1000.0, seconds=4.0, rms=4.0, band=(2.0, 30.0), noise=0.01, keep=("a",)
) -> tuple[symsbl.Trajectory, symsbl.Trajectory]:
    """An accelerometer's record ``a`` (with ``noise`` times its spread, white) and the clean record of ``x``,
    ``v``, ``a`` it was taken from."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(seconds * fs)) + 1) / fs
    force = multisine(rms, band[0], band[1], seconds, rng)
    clean = simulate(plant, force, t)
    f = force(t)
    a = accelerations(plant, clean, f)
    columns = np.column_stack([clean, a])
    truth = symsbl.Trajectory(t, columns, f[:, None], ("x", "v", "a"), ("F",))
    noisy = columns + noise * columns.std(axis=0) * rng.standard_normal(columns.shape)
    measured = symsbl.Trajectory(t, noisy, f[:, None], ("x", "v", "a"), ("F",)).with_states(list(keep))
    return measured, truth


@dataclasses.dataclass(frozen=True)
class Chain:
    """Two masses in a chain: ground - (k1, c1, cubic k3, Coulomb fc on mass 1) - m1 - (k2, c2) - m2, the force on
    mass 2.

    ``m1 x1'' = -k1 x1 - c1 v1 - k3 x1^3 - fc sign(v1) + k2 (x2 - x1) + c2 (v2 - v1)``,
    ``m2 x2'' = F - k2 (x2 - x1) - c2 (v2 - v1)``.
    """

    m1: float = 1.3
    m2: float = 0.8
    k1: float = 2.0e3
    k2: float = 1.2e3
    c1: float = 1.6
    c2: float = 0.9
    k3: float = 3.0e7
    fc: float = 0.0

    def rhs(self, s, force):
        x1, v1, x2, v2 = s
        spring = self.k2 * (x2 - x1) + self.c2 * (v2 - v1)
        a1 = (-self.k1 * x1 - self.c1 * v1 - self.k3 * x1**3 - self.fc * np.sign(v1) + spring) / self.m1
        a2 = (force - spring) / self.m2
        return np.array([v1, a1, v2, a2])

    def truth(self) -> dict:
        """The true coefficients of ``v1'`` and ``v2'`` in symsbl's term names."""
        v1 = {
            "x1": -(self.k1 + self.k2) / self.m1,
            "v1": -(self.c1 + self.c2) / self.m1,
            "x2": self.k2 / self.m1,
            "v2": self.c2 / self.m1,
            "x1**3": -self.k3 / self.m1,
        }
        if self.fc:
            v1["sign(v1)"] = -self.fc / self.m1
        v2 = {
            "x1": self.k2 / self.m2,
            "v1": self.c2 / self.m2,
            "x2": -self.k2 / self.m2,
            "v2": -self.c2 / self.m2,
            "F": 1 / self.m2,
        }
        return {"v1": v1, "v2": v2}

    def record(
        self, seed: int, *, fs=1000.0, seconds=4.0, rms=5.0, band=(2.0, 40.0), noise=0.01, substeps=16
    ) -> tuple[symsbl.Trajectory, symsbl.Trajectory]:
        """Accelerometers ``a1``, ``a2`` with ``noise`` times their spread, and the clean record of every state and
        acceleration, by classical RK4 at ``substeps`` per sample on the analytic force (written here, not
        symsbl's)."""
        rng = np.random.default_rng(seed)
        n = int(round(seconds * fs)) + 1
        t = np.arange(n) / fs
        force = multisine(rms, band[0], band[1], seconds, rng)
        h = 1.0 / (fs * substeps)
        half = force(np.arange(2 * substeps * (n - 1) + 1) * (h / 2))  # the force at every half step
        s, out = np.zeros(4), np.empty((n, 4))
        for i in range(n):
            out[i] = s
            if i == n - 1:
                break
            for j in range(substeps):
                q = 2 * (i * substeps + j)
                k1 = self.rhs(s, half[q])
                k2 = self.rhs(s + h / 2 * k1, half[q + 1])
                k3 = self.rhs(s + h / 2 * k2, half[q + 1])
                k4 = self.rhs(s + h * k3, half[q + 2])
                s = s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        f = force(t)
        acc = np.array([self.rhs(row, fi)[[1, 3]] for row, fi in zip(out, f)])
        columns = np.column_stack([out, acc])
        names = ("x1", "v1", "x2", "v2", "a1", "a2")
        truth = symsbl.Trajectory(t, columns, f[:, None], names, ("F",))
        noisy = columns + noise * columns.std(axis=0) * rng.standard_normal(columns.shape)
        return symsbl.Trajectory(t, noisy, f[:, None], names, ("F",)).with_states(["a1", "a2"]), truth
