"""Two tanks in cascade with the upper level hidden: its law found from the lower level and the inflow.

Water pumped into an upper tank drains through an orifice into a lower one, which drains in turn
(Torricelli's law, the outflow as the square root of the level)::

    x1' = -k1 sqrt(x1) + k4 u        (upper level, not measured)
    x2' =  k2 sqrt(x1) - k3 sqrt(x2)  (lower level, measured)

The inflow is a multisine around 1 (10 min at 5 Hz), the lower level carries 0.5 % noise. With
``x1`` asked for in ``states`` and absent from the record, ``identify`` screens laws
``x1' = d - a phi(x1)`` simulated from the measured signals and refines the best by output error. A
latent level is known up to a scale (``sqrt(s x1) = sqrt(s) sqrt(x1)``): the model holds the inflow's
coefficient at 1, so its ``x1`` is the true level divided by ``k4``.
"""

import math

import casadi as ca
import numpy as np

import symsbl

K1, K2, K3, K4 = 0.5, 0.5, 0.4, 0.4
FS, SPAN, NOISE = 5.0, 600.0, 0.005


def inflow(seed: int) -> np.ndarray:
    """A flow around 1 with 59 random-phase tones up to 0.1 Hz."""
    t = np.arange(int(SPAN * FS)) / FS
    rng = np.random.default_rng(seed)
    tones = sum(np.cos(2 * np.pi * k / SPAN * t + rng.uniform(0, 2 * np.pi)) for k in range(1, 60))
    return 1.0 + 0.25 * tones / math.sqrt(59 / 2)


def records():
    """The training and held-out records (lower level and inflow) and their noise-free levels."""
    x1, x2, u = symsbl.symbols("x1 x2 u")
    tanks = symsbl.OdeSystem(
        states=(x1, x2), inputs=(u,), rhs=(-K1 * ca.sqrt(x1) + K4 * u, K2 * ca.sqrt(x1) - K3 * ca.sqrt(x2))
    )
    rest = [(K4 / K1) ** 2, (K2 * K4 / (K1 * K3)) ** 2]  # the levels at u = 1
    out = []
    for seed in (0, 1):
        flow = inflow(seed)
        t = np.arange(flow.size) / FS
        clean = symsbl.simulate(tanks, t, inputs=flow, x0=rest)
        level = clean.column("x2")
        noisy = level + NOISE * level.std() * np.random.default_rng(10 + seed).standard_normal(t.size)
        out.append((symsbl.Trajectory(t, noisy[:, None], flow[:, None], ("x2",), ("u",)), clean))
    return out


def main():
    """Identify, print, check against the truth, and return the model and both records (the gallery draws
    them)."""
    (train, _), (held, truth) = records()
    x1, x2, u = symsbl.symbols("x1 x2 u")
    library = symsbl.polynomial([x1, x2], 2) + symsbl.elementwise([x1, x2], ["sqrt"]) + symsbl.inputs([u])
    model = symsbl.identify(train, library, states=("x1", "x2"))
    print(model)
    info = model.metadata["latent"]
    print(f"verdict: {info['verdict']}; log evidence by branch:")
    for name, branch in info["branches"].items():
        print(f"  {name}: {branch['log_evidence']:.1f}")
    check = symsbl.validate_model(model, held)
    print(f"held-out lower level: {check}")

    scale = math.sqrt(K4)  # the model's x1 is x1 / K4
    true = {("x1", "sqrt(x1)"): -K1 / scale, ("x2", "sqrt(x1)"): K2 * scale, ("x2", "sqrt(x2)"): -K3}
    found = {(eq.lhs, t.name): t.coef for eq in model.equations for t in eq.terms if not t.fixed}
    for (lhs, term), value in true.items():
        print(f"{lhs}': {term} {found.get((lhs, term), 0.0):+.4f} (true {value:+.4f})")
    assert set(found) == set(true), found
    assert all(abs(found[k] / v - 1) < 0.01 for k, v in true.items())
    assert check.nrmse["x2"] < 1.1 * NOISE  # at the noise floor
    return model, held, truth


if __name__ == "__main__":
    main()
