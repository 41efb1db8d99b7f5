"""Latent states: a hysteretic force identified from the position alone (symsbl._latent).

References: the systems that generated the records (their parameters are known), the analytic derivative
of a periodic signal, the noise variance that was added, and a brute-force period search.
"""

import json

import casadi as ca
import numpy as np
import pytest

import symsbl
from symsbl._latent import Spectra, split_periods, whole_record
from symsbl._latent.skeleton import fit_linear

FS = 1000.0
PERIOD = 4.096  # s: 4096 samples
N = int(PERIOD * FS)


def forcing(rms, seed, periods):
    """A multisine (4-100 Hz) sampled over whole periods, interpolated band-limited between samples (exact
    for it, and ~50x cheaper to integrate than its 393 sines)."""
    t = np.arange(periods * N) / FS
    return t, symsbl.Sampled(
        t, symsbl.Multisine(rms=rms, f_min=4.0, f_max=100.0, seed=seed, period=PERIOD)(t), kind="periodic"
    )


def periodic_record(system, *, rms=40.0, seed=1, periods=4, warm=2, noise=0.01, noise_seed=5):
    """Steady-state periods of ``system`` under a multisine, position only, with white noise."""
    t, u = forcing(rms, seed, warm + periods)
    clean = symsbl.simulate(system, t, inputs=u, method="rk4", substeps=8).slice(warm * N)
    x = clean.column("x1")
    rng = np.random.default_rng(noise_seed)
    measured = x + noise * x.std() * rng.standard_normal(x.size)
    record = symsbl.Trajectory(clean.t - clean.t[0], measured[:, None], clean.inputs, ("x1",), ("F",))
    return record, clean


def identify_hidden(record, **kwargs):
    x1, x2, x3, F = symsbl.symbols("x1 x2 x3 F")
    library = symsbl.paper([x1, x2, x3], [F], degree=3)
    return symsbl.identify(record, library, states=("x1", "x2", "x3"), kinematics="x1:x2", **kwargs)


def steady_state(system, rms, seed):
    """The last of three periods of ``system``'s response to a fresh multisine, from rest."""
    t, u = forcing(rms, seed, 3)
    return symsbl.simulate(system, t, inputs=u, method="rk4", substeps=8).column("x1")[2 * N :]


# -- the periodic record ------------------------------------------------------------------------------
def test_periods_found_and_transient_dropped():
    rng = np.random.default_rng(0)
    period = 500
    u1 = rng.standard_normal(period)
    u = np.concatenate([u1[-137:], np.tile(u1, 5)])  # a partial period first
    y = np.tile(np.sin(np.arange(period) / 20.0), 6)[-u.size :] + 1e-3 * rng.standard_normal(u.size)
    y[137 : 137 + period] += 0.05 * np.exp(-np.arange(period) / 100.0)  # the first whole period: a transient
    t = np.arange(u.size) / FS
    periods = split_periods(t, u, y)
    # brute force: the smallest lag at which u repeats
    lag = next(L for L in range(4, u.size // 3) if np.allclose(u[L:], u[:-L]))
    assert periods.length == lag == period
    assert periods.dropped == 1 and periods.n_periods == 4 and periods.start == 137 + period


def test_aperiodic_input_is_taken_whole():
    rng = np.random.default_rng(1)
    t = np.arange(3000) / FS
    assert split_periods(t, rng.standard_normal(t.size), rng.standard_normal(t.size)) is None
    with pytest.raises(symsbl.DataError, match=r"^data: expected a uniformly sampled record"):
        split_periods(t**1.5, rng.standard_normal(t.size), rng.standard_normal(t.size))


def test_transient_record_derivatives_and_noise_floor():
    """A record that is not periodic: derivatives away from the ends, and the noise from the floor above the band."""
    rng = np.random.default_rng(3)
    n, sd = 8000, 0.01
    t = np.arange(n) / FS
    f = np.linspace(3.0, 60.0, 40)
    phase = rng.uniform(0, 2 * np.pi, f.size)
    u = np.sin(2 * np.pi * np.outer(t, f) + phase).sum(axis=1)  # not periodic over the record
    y = (np.sin(2 * np.pi * np.outer(t, f) + phase) / f).sum(axis=1) + 0.3 * t  # with a drift
    v = (2 * np.pi * np.cos(2 * np.pi * np.outer(t, f) + phase)).sum(axis=1) + 0.3
    spectra = Spectra(whole_record(t, u, y + sd * rng.standard_normal(n)), periodic=False)
    keep = spectra.valid
    assert 0.5 * n < keep.sum() < n and not keep[0] and not keep[-1]
    assert np.sqrt(np.mean((spectra.v - v)[keep] ** 2)) < 4 * spectra.sd(spectra.iw)
    assert spectra.noise_var == pytest.approx(sd**2, rel=0.1)  # the variance that was added


def test_spectral_derivatives_and_noise_of_the_average():
    rng = np.random.default_rng(2)
    P, n = 8, 1000
    t = np.arange(n) / FS
    u = sum(np.sin(2 * np.pi * f * t + f) for f in (3.0, 5.0, 7.0, 11.0, 13.0, 17.0, 19.0, 23.0, 29.0))
    y = np.sin(2 * np.pi * 7.0 * t) + 0.3 * np.cos(2 * np.pi * 13.0 * t)
    sd = 0.01
    spectra = Spectra(
        split_periods(np.arange(P * n) / FS, np.tile(u, P), np.tile(y, P) + sd * rng.standard_normal(P * n))
    )
    v = 2 * np.pi * (7.0 * np.cos(2 * np.pi * 7.0 * t) - 0.3 * 13.0 * np.sin(2 * np.pi * 13.0 * t))
    assert np.sqrt(np.mean((spectra.v - v) ** 2)) < 4 * spectra.sd(spectra.iw)  # within its propagated noise
    assert spectra.noise_var == pytest.approx(sd**2 / P, rel=0.05)  # the variance that was added


def test_linear_skeleton_by_frequency_domain_output_error():
    system = symsbl.systems.linear(m=1.5, c=6.0, k=5e4)
    record, _ = periodic_record(system, noise=0.002)
    spectra = Spectra(split_periods(record.t, record.column("F"), record.column("x1")))
    fit = fit_linear(spectra)
    assert fit.m == pytest.approx(1.5, rel=2e-3) and fit.k == pytest.approx(5e4, rel=2e-3)
    assert fit.c == pytest.approx(6.0, rel=2e-2)
    assert abs(fit.k - 5e4) < 4 * fit.std[2]


# -- the whole pipeline --------------------------------------------------------------------------------
CASES = {
    # z' = A v - a |v| z - b v |z| (n = 1), and z' = A v - a |v| z |z| - b v z^2 (n = 2)
    "n1": dict(A=4e4, n=1, a=600.0, b=-300.0, m=1.5, c=6.0, k=3e4),
    "n2": dict(A=4e4, n=2, a=2.8, b=1.2, m=1.2, c=5.0, k=4e4),
}
#: term -> (parameter, sign, degree in x3) of the true law
LAWS = {
    "n1": {"x2": ("A", 1, 0), "x3*Abs(x2)": ("a", -1, 1), "x2*Abs(x3)": ("b", -1, 1)},
    "n2": {"x2": ("A", 1, 0), "x3*Abs(x2)*Abs(x3)": ("a", -1, 2), "x2*x3**2": ("b", -1, 2)},
}


def check_hidden_law(model, case):
    """The law of ``CASES[case]`` with its coefficients, and the skeleton's."""
    p = CASES[case]
    info = model.metadata["latent"]
    assert info["verdict"] == "hidden" and model.latent_names == ("x3",)
    law = model.equation("x3")
    assert sorted(law.names) == sorted(LAWS[case])
    v = model.equation("x2")
    assert v.coef("F") == pytest.approx(1 / p["m"], rel=1e-3)
    assert -v.coef("x1") == pytest.approx(p["k"] / p["m"], rel=5e-3)
    assert -v.coef("x2") == pytest.approx(p["c"] / p["m"], rel=2e-2)
    # the model's x3 is the true force over s (its coefficient in x2' is the convention -s/m), so a term of
    # degree d in x3 has the coefficient xi_true s^(d - 1)
    s = -next(t for t in v.terms if t.name == "x3").coef * p["m"]
    for name, (param, sign, degree) in LAWS[case].items():
        assert law.coef(name) * s ** (1 - degree) == pytest.approx(sign * p[param], rel=0.02), name


@pytest.mark.slow
def test_hidden_bouc_wen_law_found_from_the_position_alone():
    """Exponent 2 in Python (exponent 1 through the command line below)."""
    system = symsbl.systems.bouc_wen(**CASES["n2"])
    record, _ = periodic_record(system, noise=0.01)
    model = identify_hidden(record)
    check_hidden_law(model, "n2")
    # held out: a fresh multisine at 60 % of the force, in steady state
    truth = steady_state(system, 24.0, seed=7)
    predicted = steady_state(model.to_system(), 24.0, seed=7)
    assert np.sqrt(np.mean((predicted - truth) ** 2)) / truth.std() < 0.01


@pytest.mark.slow
def test_two_records_at_two_levels_jointly():
    """A test campaign: the hysteresis at 25 N and 45 N rms, fitted jointly, each record from its own initial
    state; the law is screened on the larger, and the model holds at a level between them."""
    system = symsbl.systems.bouc_wen(**CASES["n1"])
    low, _ = periodic_record(system, rms=25.0, seed=3, noise=0.01, noise_seed=8)
    high, _ = periodic_record(system, rms=45.0, seed=4, noise=0.01, noise_seed=9)
    model = identify_hidden([low, high])
    check_hidden_law(model, "n1")
    info = model.metadata["latent"]
    assert info["records"] == 2 and info["screened_on"] == 1
    assert len(model.metadata["refine"]["noise"]["x1"]["innovation_std_by_record"]) == 2
    truth = steady_state(system, 35.0, seed=11)
    predicted = steady_state(model.to_system(), 35.0, seed=11)
    assert np.sqrt(np.mean((predicted - truth) ** 2)) / truth.std() < 0.005


@pytest.mark.slow
def test_hidden_law_from_a_record_that_is_not_periodic():
    """A random-phase multisine whose period is twice the record: taken whole, its ends out of the regressions,
    refined with a cubic interpolation; the exponent-2 law is found and the held-out error is below the noise."""
    system = symsbl.systems.bouc_wen(**CASES["n2"])
    n = 8192
    t = np.arange(n) / FS
    u = symsbl.Multisine(rms=40.0, f_min=4.0, f_max=100.0, seed=21, period=2 * n / FS)
    clean = symsbl.simulate(system, t, inputs=symsbl.Sampled(t, u(t)), method="rk4", substeps=8)
    x = clean.column("x1")
    noisy = x + 0.01 * x.std() * np.random.default_rng(3).standard_normal(n)
    model = identify_hidden(symsbl.Trajectory(t, noisy[:, None], clean.inputs, ("x1",), ("F",)))
    info = model.metadata["latent"]
    assert info["verdict"] == "hidden" and not info["periodic"]
    assert sorted(model.equation("x3").names) == sorted(LAWS["n2"])
    truth = steady_state(system, 24.0, seed=7)
    predicted = steady_state(model.to_system(), 24.0, seed=7)
    assert np.sqrt(np.mean((predicted - truth) ** 2)) / truth.std() < 0.01  # 0.44 %: the noise is 1 %


def chain_with_dahl_friction(m1=1.6, m2=0.8, k1=2.5e4, k2=1.2e4, c1=5.0, c2=2.0, s=3e4, Fc=6.0):
    """Two masses, the first held to the ground by a spring, a damper and Dahl friction (``z' = s v1 - (s / Fc)
    |v1| z``), the force on the second."""
    y1, v1, y2, v2, z, F = (ca.SX.sym(n) for n in ("y1", "v1", "y2", "v2", "z", "F"))
    rhs = (
        v1,
        (-k1 * y1 - c1 * v1 - k2 * (y1 - y2) - c2 * (v1 - v2) - z) / m1,
        v2,
        (F - k2 * (y2 - y1) - c2 * (v2 - v1)) / m2,
        s * v1 - (s / Fc) * ca.fabs(v1) * z,
    )
    return symsbl.OdeSystem((y1, v1, y2, v2, z), (F,), rhs, (), (), "chain_dahl")


def chain_response(system, rms, seed, periods, period=2.0):
    t = np.arange(int(periods * period * FS)) / FS
    u = symsbl.Multisine(rms=rms, f_min=2.0, f_max=80.0, seed=seed, period=period)
    return symsbl.simulate(system, t, inputs=symsbl.Sampled(t, u(t), kind="periodic"), method="rk4", substeps=8)


def identify_chain(system, rms, seed, noise, noise_seed):
    """Three steady-state periods of both positions, with white noise, identified with the friction's state
    latent."""
    clean = chain_response(system, rms=rms, seed=seed, periods=4).slice(int(2.0 * FS))
    rng = np.random.default_rng(noise_seed)
    noisy = [clean.column(n) + noise * clean.column(n).std() * rng.standard_normal(clean.t.size) for n in ("y1", "y2")]
    record = symsbl.Trajectory(clean.t - clean.t[0], np.column_stack(noisy), clean.inputs, ("y1", "y2"), ("F",))
    y1, v1, y2, v2, z, F = symsbl.symbols("y1 v1 y2 v2 z F")
    library = symsbl.paper([y1, v1, y2, v2, z], [F], degree=3)
    return symsbl.identify(record, library, states=("y1", "v1", "y2", "v2", "z"), kinematics="y1:v1,y2:v2")


def chain_errors(system, model, rms, seed) -> dict:
    """Each position's free-run error over the second period of a fresh multisine from rest, relative to its
    spread."""
    truth, predicted = (chain_response(s, rms=rms, seed=seed, periods=2) for s in (system, model.to_system()))
    tail = slice(int(2.0 * FS), None)  # the initial transient gone
    return {
        n: float(
            np.sqrt(np.mean((predicted.column(n)[tail] - truth.column(n)[tail]) ** 2)) / truth.column(n)[tail].std()
        )
        for n in ("y1", "y2")
    }


def test_host_and_drives_of_a_chain_whatever_the_order_of_its_pairs():
    """The host is the mass whose linear fit leaves most beyond its noise, listed first or not; on a linear chain
    both drives are the true coupling: of the driven mass, in the input's units (k2, c2, 1), of the other, per
    unit mass (k2/m1, c2/m1)."""
    from symsbl._latent.hosts import drives, host_of, same_cut

    def spectra_of(system, noise):
        clean = chain_response(system, rms=25.0, seed=1, periods=7).slice(int(4 * 2.0 * FS))  # the transient gone
        rng = np.random.default_rng(4)
        y = {
            n: clean.column(n) + noise * clean.column(n).std() * rng.standard_normal(clean.t.size) for n in ("y1", "y2")
        }
        cut = split_periods(clean.t, clean.column("F"), y["y2"])
        out = {n: Spectra(same_cut(cut, y[n])) for n in y}
        return out, {"F": out["y2"].u}

    pairs = (("y2", "v2"), ("y1", "v1"))  # the host second
    spectra, inputs = spectra_of(chain_with_dahl_friction(), 0.005)
    host, misfit = host_of(spectra, pairs, inputs)
    assert host == ("y1", "v1") and misfit["y1"] > 2 and 0.7 < misfit["y2"] < 1.4
    spectra, inputs = spectra_of(chain_with_dahl_friction(s=0.0), 1e-6)  # nothing hidden: a linear chain
    truth = {("y2", "v2"): {"y1": 1.2e4, "v1": 2.0, "F": 1.0}, ("y1", "v1"): {"y2": 1.2e4 / 1.6, "v2": 2.0 / 1.6}}
    for host, expected in truth.items():
        for drive in drives(spectra, pairs, inputs, host):
            assert drive.driven == ("F" in expected)
            terms = dict(drive.terms)
            for name, value in expected.items():
                assert terms[name] == pytest.approx(value, rel=1e-3), (host, drive.kind, name)


@pytest.mark.slow
def test_hidden_friction_on_one_mass_of_a_chain():
    """Both positions measured, the friction's state hidden, the force on the other mass: the host is found (its
    hidden force has a law, the other's does not), the law and every coefficient within 1 %, and a fresh
    multisine predicted far below the noise's level."""
    system = chain_with_dahl_friction()
    model = identify_chain(system, rms=25.0, seed=1, noise=0.005, noise_seed=4)
    info = model.metadata["latent"]
    assert info["verdict"] == "hidden" and info["host"] == "y1"
    assert info["misfit"]["y1"] > 2 and 0.7 < info["misfit"]["y2"] < 1.4  # the second mass: linear, to its noise
    assert info["drive"] == "free" and not info["driven"]
    lead = max(info["branches"].values(), key=lambda b: b["log_evidence"])
    assert info["chosen"] == "hidden" and info["branches"]["hidden"] is lead
    # the margin the verdict asked the hidden branch to win by, and no rival within it
    assert info["margin"] > 0 and info["rivals"] == {}
    others = [b["log_evidence"] for b in info["branches"].values() if b is not lead]
    assert all(lead["log_evidence"] - e > info["margin"] for e in others)
    from symsbl._cli import _latent_summary

    assert _latent_summary(info).startswith("latent state z on y1 (each position's linear misfit over its noise")
    law, host = model.equation("z"), model.equation("v1")
    assert sorted(law.names) == ["v1", "z*Abs(v1)"]
    scale = -host.coef("z")  # the model's z is the friction force times scale / m1
    assert law.coef("z*Abs(v1)") == pytest.approx(-3e4 / 6.0, rel=0.01)
    assert law.coef("v1") * scale == pytest.approx(3e4 / 1.6, rel=0.01)
    truth = {"y1": -(2.5e4 + 1.2e4) / 1.6, "y2": 1.2e4 / 1.6, "v1": -7.0 / 1.6, "v2": 2.0 / 1.6}
    assert sorted(host.names) == sorted([*truth, "z"])
    for name, value in truth.items():
        assert host.coef(name) == pytest.approx(value, rel=0.01), name
    assert model.equation("v2").coef("F") == pytest.approx(1 / 0.8, rel=0.01)
    assert max(chain_errors(system, model, rms=20.0, seed=7).values()) < 0.001  # measured: 0.025 %


@pytest.mark.slow
def test_hysteresis_on_the_driven_mass_of_a_chain():
    """A Bouc-Wen hysteresis on the mass the force drives: the host's own least-squares fit books the hysteresis
    on its neighbour's damping (-30 against +2), and the reciprocal drive (the neighbour's own coupling to the
    host, times one ratio) is the one the split keeps; a fresh multisine is predicted within 1 %."""
    y1, v1, y2, v2, z, F = (ca.SX.sym(n) for n in ("y1", "v1", "y2", "v2", "z", "F"))
    rhs = (
        v1,
        F - 3e4 * y1 - 3.0 * v1 - 2e4 * (y1 - y2) - 2.0 * (v1 - v2) - z,
        v2,
        (-2e4 * (y2 - y1) - 2.0 * (v2 - v1)) / 1.5,
        3e4 * v1 - 500.0 * ca.fabs(v1) * z + 200.0 * v1 * ca.fabs(z),
    )
    system = symsbl.OdeSystem((y1, v1, y2, v2, z), (F,), rhs, (), (), "chain_bouc_wen")
    model = identify_chain(system, rms=40.0, seed=5, noise=0.01, noise_seed=9)
    info = model.metadata["latent"]
    assert info["verdict"] == "hidden" and info["host"] == "y1"
    assert info["drive"] == "reciprocal" and info["driven"]
    assert model.equation("v1").coef("F") == pytest.approx(1.0, rel=0.01)
    assert max(chain_errors(system, model, rms=30.0, seed=8).values()) < 0.01  # measured: 0.37 %


@pytest.mark.slow
def test_nothing_hidden_in_a_linear_oscillator():
    record, _ = periodic_record(symsbl.systems.linear(m=1.5, c=6.0, k=5e4), noise=0.01)
    model = identify_hidden(record)
    info = model.metadata["latent"]
    assert info["verdict"] == "nothing hidden (linear)"
    assert model.equation("x3").terms == () and model.equation("x2").names == ["F", "x1", "x2"]
    assert model.equation("x2").coef("F") == pytest.approx(1 / 1.5, rel=1e-3)
    doc = model.to_json()
    assert doc["latent"] == {"x3": "not needed: no equation uses it (nothing hidden)"}
    assert str(symsbl.IdentifiedModel.from_json(json.dumps(doc, default=float))) == str(model)


# -- errors --------------------------------------------------------------------------------------------
def test_settings_outside_the_one_identified_are_refused():
    t = np.arange(64) / FS
    record = symsbl.Trajectory(t, np.sin(t)[:, None], np.cos(t)[:, None], ("x1",), ("F",))
    x1, x2, x3, x4, F = symsbl.symbols("x1 x2 x3 x4 F")
    library = symsbl.paper([x1, x2, x3, x4], [F], degree=2)
    refused = r"^states: expected one latent state beside measured states"
    with pytest.raises(symsbl.DataError, match=refused):  # two latent states
        symsbl.identify(record, library, states=("x1", "x2", "x3", "x4"), kinematics="x1:x2")
    level = symsbl.Trajectory(t, np.column_stack([np.sin(t), np.cos(t)]), np.cos(t)[:, None], ("x1", "x3"), ("F",))
    with pytest.raises(symsbl.DataError, match=refused):  # a measured state outside a pair whose velocity is not
        symsbl.identify(level, library, states=("x1", "x2", "x3", "x4"), kinematics="x1:x2")
    (x5,) = symsbl.symbols("x5")
    library = symsbl.paper([x1, x2, x3, x4, x5], [F], degree=1)
    velocity = symsbl.Trajectory(t, np.column_stack([np.sin(t), np.cos(t)]), np.cos(t)[:, None], ("x1", "x4"), ("F",))
    with pytest.raises(symsbl.DataError, match=r"^state 'x3': expected a column of the data \(a measured position\)"):
        symsbl.identify(velocity, library, states=("x1", "x2", "x3", "x4", "x5"), kinematics="x1:x2,x3:x4")


def test_options_the_latent_path_cannot_honour_are_refused_in_one_line():
    """No equation-error model to return, no derivative but the record's own weak form; refused before any work."""
    t = np.arange(64) / FS
    record = symsbl.Trajectory(t, np.sin(t)[:, None], np.cos(t)[:, None], ("x1",), ("F",))
    x1, x2, x3, F = symsbl.symbols("x1 x2 x3 F")
    library = symsbl.paper([x1, x2, x3], [F], degree=2)
    kw = dict(states=("x1", "x2", "x3"), kinematics="x1:x2")
    with pytest.raises(symsbl.ParameterError, match=r"^refine: expected True or a RefineOptions when a state is lat"):
        symsbl.identify(record, library, refine=False, **kw)
    for derivative in ("central", symsbl.WeakForm(overlap=2)):
        with pytest.raises(symsbl.ParameterError, match=r"^derivative: expected 'weak' when a state is latent"):
            symsbl.identify(record, library, derivative=derivative, **kw)


def test_branch_options_are_the_callers_with_the_latent_paths_defaults_resolved():
    from symsbl._latent import Fitting

    default = Fitting().branch_options(periodic=True, band_substeps=4)
    assert (default.interpolation, default.substeps, default.min_substeps, default.doubts) == (
        "periodic",
        "auto",
        4,
        "report",
    )
    assert Fitting().branch_options(periodic=False, band_substeps=4).interpolation == "cubic"
    asked = Fitting(options=symsbl.RefineOptions(interpolation="hold", substeps=7, noise="white", max_samples=999))
    given = asked.branch_options(periodic=True, band_substeps=4)
    assert (given.interpolation, given.substeps, given.noise, given.max_samples) == ("hold", 7, "white", 999)
    assert Fitting(rule=symsbl.SelectionRule(penalty=12.5)).template.prune_nats == 12.5
    assert Fitting(rvm=symsbl.RVM(tol=1e-5)).template.get_params()["tol"] == 1e-5


def test_the_winner_is_refined_again_only_where_the_caller_asked_otherwise(monkeypatch):
    """The branches report their doubts and choose by evidence; the winner is refined once more when the caller's
    rule still chooses a structure, or when it was doubted and the caller adapts to doubts (with or without
    term selection), and then with the caller's doubts."""
    from types import SimpleNamespace

    import symsbl._latent as latent

    calls = []
    monkeypatch.setattr(latent, "refine", lambda fit, data, **kw: calls.append(kw["options"]) or fit)
    clean = SimpleNamespace(metadata={"refine": {"doubts": []}})
    doubted = SimpleNamespace(metadata={"refine": {"doubts": ["the innovations of x1 are not white"]}})
    branch = symsbl.RefineOptions(doubts="report")
    fixed = symsbl.RefineOptions(select=False, doubts="report")
    evidence = symsbl.SelectionRule(model_choice="evidence")

    def asked(fit, options, fitting):
        calls.clear()
        latent._as_asked(fit, None, None, options, fitting, lambda stage: None)
        return [o.doubts for o in calls]

    assert asked(clean, branch, latent.Fitting(rule=evidence)) == []
    assert asked(clean, branch, latent.Fitting()) == ["adapt"]  # the validated choice
    assert asked(doubted, branch, latent.Fitting(rule=evidence)) == ["adapt"]
    assert asked(doubted, fixed, latent.Fitting(options=symsbl.RefineOptions(select=False))) == ["adapt"]
    assert asked(clean, fixed, latent.Fitting(options=symsbl.RefineOptions(select=False))) == []
    reported = symsbl.RefineOptions(doubts="report")
    assert asked(doubted, branch, latent.Fitting(options=reported, rule=evidence)) == []


@pytest.mark.slow
def test_every_option_acts_on_the_latent_path():
    """The refinement's options reach the branches, the rule's model choice the winner (an extra refinement
    only when the rule is not the branches' own), and the options are recorded as used."""
    system = symsbl.systems.bouc_wen(**CASES["n1"])
    record, _ = periodic_record(system, noise=0.01)
    asked = identify_hidden(record, refine_options=symsbl.RefineOptions(noise="white", interpolation="hold"))
    info = asked.metadata["refine"]
    assert info["interpolation"] == "hold" and info["noise"]["x1"]["model"] == "white"
    assert "as asked" in asked.metadata["latent"]["seconds"]
    by_evidence = identify_hidden(record, selection=symsbl.SelectionRule(model_choice="evidence"))
    assert "as asked" not in by_evidence.metadata["latent"]["seconds"]
    check_hidden_law(by_evidence, "n1")
    # a penalty no law can pay: the verdict is the caller's
    strict = identify_hidden(record, selection=symsbl.SelectionRule(penalty=1e7, model_choice="evidence"))
    assert strict.metadata["latent"]["verdict"].startswith("nothing hidden")


@pytest.mark.slow
def test_command_line_names_the_latent_state_and_validates_without_it(tmp_path, capsys):
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    from symsbl._cli import main

    system = symsbl.systems.bouc_wen(**CASES["n1"])
    record, _ = periodic_record(system, noise=0.01)
    symsbl.write_trajectory(record, tmp_path / "train.csv")
    held, _ = periodic_record(system, rms=24.0, seed=7, periods=2, noise=0.0)
    symsbl.write_trajectory(held, tmp_path / "held.csv")
    code = main(
        [
            "identify",
            str(tmp_path / "train.csv"),
            "--states",
            "x1,x2,x3",
            "--inputs",
            "F",
            "--kinematics",
            "x1:x2",
            "--json",
            str(tmp_path / "model.json"),
            "--quiet",
        ]
    )
    out = capsys.readouterr().out
    assert code == 0
    assert "x3: latent (not measured); scaled so that its coefficient in x2' is" in out
    assert "latent state x3: hidden; log evidence by branch: linear" in out
    doc = json.loads((tmp_path / "model.json").read_text())
    assert doc["measured"] == ["x1"] and list(doc["latent"]) == ["x3"]
    check_hidden_law(symsbl.IdentifiedModel.from_json(doc), "n1")  # the model file carries the law
    assert doc["latent"]["x3"].startswith("scaled so that its coefficient in x2' is -")
    code = main(
        [
            "validate",
            str(tmp_path / "model.json"),
            str(tmp_path / "held.csv"),
            "--json",
            str(tmp_path / "val.json"),
            "--plot",
            str(tmp_path / "fig.png"),
            "--quiet",
        ]
    )
    assert code == 0
    assert (tmp_path / "fig.png").stat().st_size > 10_000  # Figure 2: panel (b) shows x1, panel (c) the law of x3
    # the held-out record starts in steady state; its unmeasured initial velocity and force are fitted
    assert json.loads((tmp_path / "val.json").read_text())["nrmse"]["x1"] < 0.01


def test_verdict_rules():
    """The hidden branch wins by more than 1/2 log N + log M nats with a law that is not v g(z); a branch whose
    refinement diverged is absent; a memoryless branch without a force term is reported as linear."""
    import dataclasses
    from types import SimpleNamespace

    from symsbl._latent.branches import Branches
    from symsbl._latent.skeleton import Skeleton

    y, v, z, F = symsbl.symbols("y v z F")
    branches = Branches((y, v, z), F, "y", "v", "z")
    skeleton = Skeleton(2.0, 10.0, 5e4)

    def fitted(laws, evidence):
        model = branches.model(skeleton, [], laws)
        return dataclasses.replace(model, metadata={"refine": {"log_evidence": evidence}})

    def law(*terms):
        fit = SimpleNamespace(coef_=np.ones(len(terms)), active_=np.arange(len(terms)), sigma_=np.eye(len(terms)))
        return [(symsbl.Term(t), fit, i) for i, t in enumerate(terms)]

    hysteresis = law(v, ca.fabs(v) * z, v * ca.fabs(z))
    penalty = 0.5 * np.log(1000) + np.log(10)  # 5.76 nats
    linear = fitted([], 100.0)
    assert branches.verdict(
        {"linear": linear, "memoryless": linear, "hidden": fitted(hysteresis, 100 + penalty + 0.1)}, 1000, 10
    )[:2] == ("hidden", "hidden")
    assert branches.verdict(
        {"linear": linear, "memoryless": linear, "hidden": fitted(hysteresis, 100 + penalty - 0.1)}, 1000, 10
    )[:2] == ("nothing hidden (linear)", "linear")
    spring = law(v, v * ca.fabs(z))  # z' = v (1 + |z|): z = G(y), an elastic force
    assert (
        branches.verdict({"linear": linear, "memoryless": linear, "hidden": fitted(spring, 1e6)}, 1000, 10)[0]
        == "nothing hidden (linear)"
    )
    assert branches.verdict({"linear": linear, "hidden": fitted(hysteresis, 200.0)}, 1000, 10)[0] == "hidden"
    assert branches.verdict({"hidden": fitted(hysteresis, -1e9)}, 1000, 10)[:2] == ("hidden", "hidden")
