"""Shared fixtures: the paper's Duffing oscillator, simulated and identified once per test session."""

import pytest

import symsbl

#: The paper's sample rate and noise level (Fuentes et al. 2019, Sec. 3).
FS = 32768.0
NOISE = 0.004


@pytest.fixture(scope="session")
def duffing_system():
    """The paper's Duffing oscillator, x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F."""
    return symsbl.systems.duffing()


@pytest.fixture(scope="session")
def duffing_train(duffing_system):
    """1 s of the paper's 100 N, 10 Hz sine at 32768 Hz from rest, 0.4 % noise on the states."""
    clean = symsbl.simulate(duffing_system, symsbl.time_grid(1.0, FS), inputs=symsbl.Sine(100.0, 10.0))
    return clean.with_noise(NOISE, seed=0)


@pytest.fixture(scope="session")
def duffing_model(duffing_system, duffing_train):
    """The model identified from ``duffing_train`` with the Eq. 21 dictionary to degree 3."""
    return symsbl.identify(duffing_train, symsbl.paper(duffing_system.states, duffing_system.inputs, degree=3))


@pytest.fixture(scope="session")
def duffing_heldout(duffing_system):
    """0.5 s of a random-phase multisine (2-30 Hz, 60 N rms) the model never saw, 0.4 % noise."""
    forcing = symsbl.Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1)
    return symsbl.simulate(duffing_system, symsbl.time_grid(0.5, FS), inputs=forcing).with_noise(NOISE, seed=2)


@pytest.fixture(scope="session")
def duffing_short(duffing_system):
    """0.5 s of the sine at 8192 Hz, 0.4 % noise: a small record for fast checks."""
    clean = symsbl.simulate(duffing_system, symsbl.time_grid(0.5, 8192), inputs=symsbl.Sine(100.0, 10.0))
    return clean.with_noise(NOISE, seed=1)
