"""Stand-ins of an electronic Duffing oscillator whose law lies outside the library, for the model choice's tests and
benchmarks: ``x'' + 2 zeta w x' + w^2 g(x) = F`` with a restoring law ``g`` that no polynomial holds, trained on a
periodic random-phase multisine whose band reaches a third of the sampling rate, and tested on a band-limited
random force whose amplitude grows past the training one (what a user does next: simulate beyond the record).

The simulator is independent of symsbl's: numpy RK4 at 8 substeps per sample with the input linear between
samples.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

import symsbl

W = 2 * np.pi * 50.0
FS = 610.0


def saturating(x: np.ndarray) -> np.ndarray:
    """A hardening that saturates: ``x + 400 x^3 / (1 + (x / 0.05)^2)`` (cubic at small x, linear at large)."""
    return x + 400.0 * x**3 / (1.0 + (x / 0.05) ** 2)


def piecewise(x: np.ndarray) -> np.ndarray:
    """A stiffness that grows by half beyond a clearance of 0.02: ``x + 0.5 (|x| - 0.02)_+ sign(x)`` (tripling it
    made the multisine's response chaotic)."""
    return x + 0.5 * np.maximum(np.abs(x) - 0.02, 0.0) * np.sign(x)


@dataclass(frozen=True)
class Oscillator:
    """``x'' + 2 zeta w x' + w^2 law(x) = F`` sampled at ``fs``."""

    law: Callable[[np.ndarray], np.ndarray] = saturating
    w: float = W
    zeta: float = 0.04
    fs: float = FS

    def rhs(self, s: np.ndarray, force: float) -> np.ndarray:
        x, v = s
        return np.array([v, force - 2 * self.zeta * self.w * v - self.w**2 * self.law(x)])

    def simulate(self, u: np.ndarray, substeps: int = 8) -> np.ndarray:
        """States ``(x, v)`` at each sample from rest under the force ``u`` (linear between samples)."""
        h, s, out = 1.0 / (substeps * self.fs), np.zeros(2), np.empty((u.size, 2))
        for i in range(u.size):
            out[i] = s
            u0, u1 = u[i], u[min(i + 1, u.size - 1)]
            for j in range(substeps):
                a, b = u0 + (u1 - u0) * j / substeps, u0 + (u1 - u0) * (j + 1) / substeps
                k1 = self.rhs(s, a)
                k2 = self.rhs(s + h / 2 * k1, (a + b) / 2)
                k3 = self.rhs(s + h / 2 * k2, (a + b) / 2)
                k4 = self.rhs(s + h * k3, b)
                s = s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        return out


def multisine(n: int, band: float, rng: np.random.Generator) -> np.ndarray:
    """One period of ``n`` samples of unit rms, random phases, flat on the lines below ``band`` of the sampling
    rate."""
    spectrum = np.zeros(n // 2 + 1, complex)
    lines = np.arange(1, int(band * n))
    spectrum[lines] = np.exp(2j * np.pi * rng.uniform(size=lines.size))
    u = np.fft.irfft(spectrum, n)
    return u / u.std()


def measured(
    plant: Oscillator, u: np.ndarray, states: np.ndarray, noise: float, input_noise: float, rng
) -> symsbl.Trajectory:
    """The record of ``states`` and ``u`` with white noise of ``noise`` (x, v) and ``input_noise`` (F) of each
    channel's spread."""
    y = states + noise * states.std(axis=0) * rng.standard_normal(states.shape)
    force = u + input_noise * u.std() * rng.standard_normal(u.size)
    return symsbl.Trajectory(np.arange(u.size) / plant.fs, y, force[:, None], ("x", "v"), ("F",))


def training(
    plant: Oscillator,
    seed: int = 0,
    *,
    length: int = 4096,
    periods: int = 3,
    band: float = 0.3,
    rms: float = 2000.0,
    noise: float = 0.005,
    input_noise: float = 0.001,
) -> symsbl.Trajectory:
    """``periods`` periods of a multisine of ``rms`` to ``band`` * fs, the first dropped as transient."""
    rng = np.random.default_rng(seed)
    u = rms * np.tile(multisine(length, band, rng), periods)
    states = plant.simulate(u)
    return measured(plant, u[length:], states[length:], noise, input_noise, rng)


def extrapolating(
    plant: Oscillator,
    seed: int = 100,
    *,
    n: int = 12288,
    band: float = 0.3,
    rms: float = 2000.0,
    growth: tuple[float, float] = (0.3, 1.6),
    noise: float = 0.005,
) -> symsbl.Trajectory:
    """A random force band-limited to ``band`` * fs whose amplitude ramps from ``growth[0]`` to ``growth[1]`` times
    the training ``rms`` (the last third beyond the training range)."""
    rng = np.random.default_rng(seed)
    spectrum = np.fft.rfft(rng.standard_normal(n))
    spectrum[np.fft.rfftfreq(n) > band] = 0.0
    u = np.fft.irfft(spectrum, n)
    u = rms * u / u.std() * np.linspace(*growth, n)
    return measured(plant, u, plant.simulate(u), noise, 0.0, rng)
