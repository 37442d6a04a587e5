"""Discovery beyond the catalog: a planted function is learned where it acts and its
truth recovered; the held-out check refuses a term that only fits noise; the distilled
equation has the planted form; a mains hum is an artefact, not physics.

The traces come from the synthetic rig (:mod:`ewb_ident.rig`) with a term the catalog
does not hold written onto its noise-free recording here.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import re

import numpy as np
import pytest

from ewb_ident import rig
from ewb_ident.data.outputs import json_text
from ewb_ident.diagnosis import discovery as disc_mod
from ewb_ident.diagnosis import filters, heldout, inputs, places
from ewb_ident.diagnosis.diagnose import diagnose

SETTINGS = dict(seed=5, sample_rate_hz=200.0, duration_s=3.0, profile="position")
DAMPING_NS_PER_M = 2.0e4  # N per (m/s)
PRESSURE_K = 0.15  # mu falls by 15 % at the rated force


@functools.cache
def _clean():
    noise = rig.SensorNoise()
    trace, _, run = rig.simulate_rig(rig.RigParams(), noise=noise, return_clean=True, **SETTINGS)
    return trace, run, noise


def _with(channels: dict[str, np.ndarray], name: str):
    trace, run, noise = _clean()
    rng = np.random.default_rng(17)
    ch = dict(trace.channels)
    for c, clean in channels.items():
        ch[c] = clean + noise.sigma(c) * rng.standard_normal(trace.n)
    return dataclasses.replace(trace, channels=ch, name=name)


def damped_force_trace():
    """The force reading carries a viscous term c dx/dt (a damper the model lacks)."""
    trace, run, _ = _clean()
    xr = np.gradient(run.states["x_m"], trace.dt)
    return _with({"force_N": run.states["force_N"] + DAMPING_NS_PER_M * xr}, "damped")


def pressure_friction_trace():
    """The friction coefficient falls with the pad pressure, mu (1 - k F / F_rt)."""
    trace, run, _ = _clean()
    F = run.states["force_N"]
    return _with({"torque_Nm": run.states["torque_Nm"] * (1 - PRESSURE_K * F / 3500.0)}, "mu_F")


@functools.cache
def damped_diagnosis():
    return diagnose(damped_force_trace())


@functools.cache
def pressure_diagnosis():
    return diagnose(pressure_friction_trace())


def test_a_planted_term_is_learned_where_it_acts_and_its_truth_recovered():
    res = damped_diagnosis()
    assert res.verdict == "unexplained"  # located, and no catalog name for it
    assert not any(f.catalog for f in res.findings)
    top = res.findings[0]
    assert top.place in ("sensor.force_N", "force.output")  # the force reading / law
    assert top.depends_on == ("x_rate",)
    (term,) = top.terms
    assert term["expression"] == "dx/dt"
    assert term["coef"] == pytest.approx(DAMPING_NS_PER_M, rel=0.05)
    # The learned series is the planted one (against the truth, not a lower residual).
    trace, run, _ = _clean()
    truth = DAMPING_NS_PER_M * np.gradient(run.states["x_m"], trace.dt)
    err = np.sqrt(np.mean((top.term_series - truth) ** 2))
    assert err < 0.1 * np.sqrt(np.mean(truth**2))
    assert top.heldout["excess_share"] >= 0.8
    assert top.heldout["method"].startswith("4-fold blocked")


RUNOUT_PERIOD_DEG = 51.4  # a worm with 7 teeth a turn: a period in no list
RUNOUT_DEG = 1.0


def runout_trace():
    """A periodic transmission error: the piston follows the pinion angle plus
    ``A sin(2 pi theta / P + phase)``, at a period no list of candidates holds."""
    trace, run, _ = _clean()
    th = run.states["theta_deg"]
    p = rig.RigParams()
    th_w = th + RUNOUT_DEG * np.sin(2 * np.pi * th / RUNOUT_PERIOD_DEG + 0.7)
    return _with({"x_m": p.p2 * th_w**2 + p.p1 * th_w + p.p0}, "runout")


def test_a_periodic_term_is_found_at_the_period_the_residual_shows():
    """The period comes from the residual (a periodogram in the angle), not a list: the
    learned term acts at the gap curve, depends on the angle, and its distilled period,
    amplitude and series match the planted ones."""
    res = diagnose(runout_trace())
    (top,) = res.findings
    assert top.place == "gap" and top.depends_on == ("angle",)
    th = _clean()[1].states["theta_deg"]
    _assert_harmonic(top, r"Δθ = (.+)·sin\(2πθ/(.+)° .+\) \[deg\]", th, RUNOUT_DEG,
                     RUNOUT_PERIOD_DEG, 0.7)  # fmt: skip


def _assert_harmonic(top, pattern: str, pos, amp: float, period: float, phase: float, unit=1.0):
    """The finding's equation is one harmonic of ``pos`` at the planted period (its unit
    ``unit`` of the position's) and amplitude, and its series is the planted one."""
    m = re.fullmatch(pattern, top.equation)
    assert m, top.equation
    assert float(m.group(2)) * unit == pytest.approx(period, rel=0.01)
    assert float(m.group(1)) == pytest.approx(amp, rel=0.15)
    truth = amp * np.sin(2 * np.pi * pos / period + phase)
    assert np.sqrt(np.mean((top.term_series - truth) ** 2)) < 0.25 * np.sqrt(np.mean(truth**2))
    assert top.heldout["excess_share"] >= 0.8


SCALE_PITCH_M = 0.27e-3  # a period in x in no list, some six cycles over the stroke
SCALE_ERROR_M = 8e-6


def scale_trace():
    """A linear scale's interpolation error: the displacement reads
    ``x + A sin(2 pi x / P + phase)``, periodic in x, not in the angle (the gap curve
    stretches one against the other by a factor of three over the stroke)."""
    trace, run, _ = _clean()
    x = run.states["x_m"]
    return _with({"x_m": x + SCALE_ERROR_M * np.sin(2 * np.pi * x / SCALE_PITCH_M + 0.4)}, "scale")


def test_a_term_periodic_in_the_displacement_is_found_in_x_not_in_the_angle():
    """The periodogram runs in each position a place feels: a scale's error, periodic
    in x, is learned at the displacement sensor on x at the planted period (the runout
    above, periodic in the angle at the same stage, stays on the angle)."""
    res = diagnose(scale_trace())
    (top,) = res.findings
    assert top.place == "sensor.x_m" and top.depends_on == ("x",)
    x = _clean()[1].states["x_m"]
    _assert_harmonic(top, r"Δx_m = (.+)·sin\(2πx/(.+) mm .+\) \[m\]", x, SCALE_ERROR_M,
                     SCALE_PITCH_M, 0.4, unit=1e-3)  # fmt: skip
    assert "scale" in top.reading


RIPPLE = 0.04  # the clamping force varies by 4 % around a disc turn


def test_a_coefficient_that_varies_around_the_disc_is_learned_as_a_product():
    """A disc of uneven thickness: the clamping force is ``F (1 + e sin(phi_d + phase))``
    around each turn of the disc. The learned function multiplies the force by a
    harmonic of the disc angle (a carrier times a periodic input), and the distilled
    equation is that product with the planted amplitude."""
    trace, run, _ = _clean()
    F = run.states["force_N"]
    truth = RIPPLE * F * np.sin(inputs.disc_angle(trace) + 0.4)
    res = diagnose(_with({"force_N": F + truth}, "thickness"))
    (top,) = res.findings
    assert top.place in ("force.output", "sensor.force_N")
    assert set(top.depends_on) == {"force", "disc_angle"}
    m = re.fullmatch(
        r"Δ(?:F|force_N) = \+?([0-9.e+-]+)·F·sin\(φ_d ([+-][0-9.]+)\) \[N\]", top.equation
    )
    assert m, top.equation
    assert float(m.group(1)) == pytest.approx(RIPPLE, rel=0.1)
    assert float(m.group(2)) == pytest.approx(0.4, abs=0.1)
    assert np.sqrt(np.mean((top.term_series - truth) ** 2)) < 0.2 * np.sqrt(np.mean(truth**2))


def test_a_term_acting_on_one_side_of_a_signed_input_is_learned_as_such():
    """A damper that acts only while the piston closes, c max(0, dx/dt) (a one-way
    valve): the learned function of a signed input is not only odd; the distilled
    equation is the one-sided hinge with the planted coefficient."""
    trace, truth = damped_recording(
        lambda xr: 2 * DAMPING_NS_PER_M * np.maximum(xr, 0.0),
        seed=5, rate_hz=200.0, duration_s=4.0, profile="staircase", noise_seed=17,
    )  # fmt: skip
    res = diagnose(dataclasses.replace(trace, name="one_way"))
    (top,) = res.findings
    assert top.depends_on == ("x_rate",)
    (term,) = top.terms
    assert term["expression"] == "max(0, dx/dt)"
    assert term["coef"] == pytest.approx(2 * DAMPING_NS_PER_M, rel=0.05)
    assert np.sqrt(np.mean((top.term_series - truth) ** 2)) < 0.15 * np.sqrt(np.mean(truth**2))


def test_the_learned_term_follows_the_contract():
    doc = json.loads(json_text(damped_diagnosis().to_json()))
    f = doc["findings"][0]
    assert {"place", "equation", "depends_on", "heldout"} <= set(f)
    assert set(f["heldout"]) >= {"improvement_pct", "method"}
    assert f["equation"].startswith("Δ") and "[N]" in f["equation"]
    assert doc["artefacts"] == []
    assert f["effect"].startswith("learned_") and f["catalog"] is False


def test_the_distilled_equation_has_the_planted_form():
    """mu (1 - k F / F_rt): a factor on the friction coefficient, linear in the force,
    its coefficient's 90 % interval holding the truth."""
    res = pressure_diagnosis()
    (top,) = res.findings
    assert top.place == "friction" and top.depends_on == ("force",)
    assert top.equation.startswith("Δμ/μ = ") and top.equation.endswith("·F [1]")
    (term,) = top.terms
    truth = -PRESSURE_K / 3500.0
    assert term["low_90"] <= truth <= term["high_90"]
    assert term["coef"] == pytest.approx(truth, rel=0.05)
    assert "pad pressure" in top.explanation  # the reading of a known signature
    # One apply: the torque rises with the force, so the trace cannot tell them apart,
    # and the finding says so; a torque added at the output as a function of the torque
    # explains it about as well, and the finding names it with its input (the damper's
    # piston speed has no such twin). The piston is no twin: its term fitted the force
    # noise the torque's residual carries only while the friction's change was scaled
    # by the recorded force.
    assert "torque" in top.equivalents and "x" not in top.equivalents
    assert "which moves with it here: the trace cannot tell" in top.explanation
    assert "the brake torque" in top.explanation.split("(or on ")[1].split(")")[0]
    assert "Terms at torque.output (on the " in top.explanation
    doc = json.loads(json_text(res.to_json()))
    assert doc["findings"][0]["depends_on_equivalent"] == list(top.equivalents)
    assert damped_diagnosis().findings[0].equivalents == ()


def test_parameters_that_depend_on_what_the_trace_cannot_tell_say_so():
    """With one torque channel a friction law in the force and a torque sensor's
    nonlinearity fit held-out data about as well, and they imply different mu: its
    interval spans both (holding the truth) and a note says why. The damper, which no
    other place explains as well, leaves a, b, c, mu as the fit gives them."""
    res = pressure_diagnosis()
    (note,) = [n for n in res.notes if "cannot pin down" in n]
    assert "mu" in note
    assert res.findings[0].basis["spread"]["mu"] > 10 * 1e-4
    mu, se = res.augmented_params["mu"], res.augmented_stderr["mu"]
    assert abs(mu - 0.35) <= 1.645 * se
    damped = damped_diagnosis()
    assert not [n for n in damped.notes if "cannot pin down" in n]
    assert damped.augmented_stderr["mu"] < 1e-3


def test_the_heldout_check_refuses_a_term_that_only_fits_noise():
    """Sixty random columns lower the in-sample residual of pure noise by several per
    cent; none of them helps data it was not fitted to, so none enters."""
    rng = np.random.default_rng(0)
    n = 1200
    fold = np.minimum((np.arange(n) * 4) // n, 3)
    cols = [inputs.Column(f"z{j}", f"s{j}", None) for j in range(60)]
    G = rng.standard_normal((n, 60))
    G /= np.linalg.norm(G, axis=0)
    d = heldout.Design(rng.standard_normal(n), np.ones((n, 1)), fold, G, float(n), 0.0, np.ones(60))
    groups = {f"g{k}": cols[6 * k : 6 * k + 6] for k in range(10)}
    before, _ = d.insample([], 0.0)
    after, _ = d.insample(list(range(60)), 0.0)
    assert after < 0.97 * before  # the columns do fit the noise in sample ...
    pf = disc_mod.learn_place(d, groups, "force.output")
    assert pf.groups == () and not pf.generalises  # ... and none is kept


def test_a_shape_that_only_two_forms_make_together_is_distilled_as_the_pair():
    """Two library forms that move nearly alike (a level and its saturation): the
    residual is their difference, which neither alone explains by the share an input
    must add, so greedy selection alone distils nothing; the pair is the expression."""
    rng = np.random.default_rng(3)
    n = 1200
    fold = np.minimum((np.arange(n) * 4) // n, 3)
    a, b = np.linalg.qr(rng.standard_normal((n, 2)))[0].T
    G = np.stack([a, a + 0.1 * b], axis=1)
    G /= np.linalg.norm(G, axis=0)
    r = 40.0 * (G[:, 0] - G[:, 1]) / np.linalg.norm(G[:, 0] - G[:, 1])
    r = r + 0.05 * rng.standard_normal(n)
    noise = float(n) * 0.05**2
    d = heldout.Design(r, np.zeros((n, 0)), fold, G, noise, 0.0, np.ones(2))
    items = [
        [inputs.Column("z", "z", None, ("pow", 1))],
        [inputs.Column("1 - exp(-z)", "z", None, ("sat", 0.3))],
    ]
    before, _ = d.best_heldout([])
    excess = before - noise
    for j in (0, 1):  # each form alone adds less than an input must
        assert before - d.heldout([j], heldout.RIDGES[0]) < disc_mod.MIN_STEP_SHARE * excess
    after = d.heldout([0, 1], heldout.RIDGES[0])
    learned = disc_mod.PlaceFit("force.input", ("z",), before, after, before, after, excess,
                                -100.0, before - after, 4, 4)  # fmt: skip
    fit, chosen, coef, _, _ = disc_mod.distil(d, items, learned, "force.input")
    assert [c[0].label for c in chosen] == ["z", "1 - exp(-z)"]
    assert fit.heldout_after < noise + 0.01 * excess and fit.generalises
    assert coef[0] * coef[1] < 0  # the difference of the two


def test_a_signal_that_is_a_monotone_function_of_a_local_one_is_read_as_it():
    """The piston's displacement is the gap curve of the pinion angle, and below the
    bell's centre the force is a function of it: a learned function of one is one of the
    other, so at the displacement sensor the angle is read as the displacement. A force
    that passes the bell's centre is no function of the displacement, and an energy that
    only grows is a clock, no twin of anything. A history of a local signal is local
    itself: it is kept, not read as the level it follows."""
    t = np.linspace(0.0, 3.0, 1500)
    angle = 400.0 * np.sin(np.pi * t / 1.5) ** 2  # two applies, deg
    x = 3.8e-9 * angle**2 + 1.5e-6 * angle - 0.00084
    bell = 3500.0 / (1.0 + np.abs((x - 0.0002) / 1e-4) ** 5.64)  # past its centre
    below = 3500.0 / (1.0 + np.abs((x - 0.0012) / 6.3e-4) ** 5.64)
    energy = np.cumsum(bell) * 1e-3
    sig = {n: inputs.Signal(n, v, "-", "level", n, n, 1.0) for n, v in
           dict(angle=angle, x=x, bell=bell, force=below, energy=energy).items()}  # fmt: skip
    twin = places.monotone_twin
    assert [twin(sig, n, ("x", "x_rate")) for n in sig] == ["x", None, None, "x", None]
    assert [twin(sig, n, ("force", "angle")) for n in sig] == [None, "force", None, None, None]
    noisy = dict(sig, angle=dataclasses.replace(sig["angle"], values=angle + 5.0 * np.sin(40 * t)))
    assert twin(noisy, "angle", ("x",)) is None
    lagged = dict(sig, force_history_0_1s=dataclasses.replace(sig["force"], name="h"))
    assert twin(lagged, "force_history_0_1s", ("force", "force_history")) is None


@pytest.mark.parametrize("rate, freq, amp", [(200.0, 50.0, 1.5), (100.0, 60.0, 1.0)])
def test_a_mains_hum_alone_is_an_artefact_and_the_verdict_none(rate, freq, amp):
    noise = rig.SensorNoise()
    trace, _ = rig.simulate_rig(
        rig.RigParams(), noise=noise, **{**SETTINGS, "sample_rate_hz": rate}
    )
    ch = dict(trace.channels)
    ch["force_N"] = ch["force_N"] + amp * noise.force_N * np.sin(2 * np.pi * freq * trace.time_s)
    res = diagnose(dataclasses.replace(trace, channels=ch, name="hum"))
    assert res.verdict == "none"
    (art,) = [a for a in res.artefacts if a.kind == "periodic_interference"]
    assert art.channel == "force_N"
    seen = freq if freq < rate / 2 else rate - freq  # 60 Hz at 100 Hz is seen at 40 Hz
    assert art.frequency_hz == pytest.approx(seen, abs=0.2)
    assert art.amplitude == pytest.approx(amp * noise.force_N, rel=0.2)
    assert "mains" in art.summary
    doc = json.loads(json_text(res.to_json()))
    assert doc["artefacts"][0]["channel"] == "force_N"


def test_a_discovered_term_is_drawn_against_what_it_depends_on():
    from ewb_ident.reporting.figures import figure_bytes

    res = damped_diagnosis()
    top = res.findings[0]
    assert top.term_input is not None and "piston speed" in top.term_input_label
    pngs = figure_bytes(res)
    name = f"finding_1_{top.effect}.png"
    assert name in pngs and pngs[name][:8] == b"\x89PNG\r\n\x1a\n"


def damped_recording(damper, seed, rate_hz, duration_s, profile, noise_seed):
    """A recording of the rig whose force carries ``damper(dx/dt)`` (N), and that term."""
    noise = rig.SensorNoise()
    trace, _, run = rig.simulate_rig(
        rig.RigParams(), noise=noise, return_clean=True, seed=seed, sample_rate_hz=rate_hz,
        duration_s=duration_s, profile=profile,
    )  # fmt: skip
    rng = np.random.default_rng(noise_seed)
    term = damper(np.gradient(run.states["x_m"], trace.dt))
    ch = dict(trace.channels)
    force = run.states["force_N"] + term
    ch["force_N"] = force + noise.sigma("force_N") * rng.standard_normal(trace.n)
    return dataclasses.replace(trace, channels=ch), term


def other_damped_trace():
    """Another recording of the same damped rig: another seed, open-loop steps, 500 Hz."""
    trace, _ = damped_recording(
        lambda xr: DAMPING_NS_PER_M * xr,
        seed=11, rate_hz=500.0, duration_s=3.0, profile="steps", noise_seed=3,
    )  # fmt: skip
    return dataclasses.replace(trace, name="damped_other")


@functools.cache
def _corrected_fit(tmp):
    """``fit --with-diagnosis`` of the damped trace's diagnosis, by the command line."""
    from pathlib import Path

    from typer.testing import CliRunner

    from ewb_ident.cli import app
    from ewb_ident.data.writers import write_trace

    tmp = Path(tmp)
    (tmp / "diagnosis.json").write_text(json_text(damped_diagnosis().to_json()))
    write_trace(damped_force_trace(), tmp / "a.csv")
    write_trace(other_damped_trace(), tmp / "b.csv")
    out = CliRunner().invoke(
        app, ["fit", str(tmp / "a.csv"), "--with-diagnosis", str(tmp), "--out", str(tmp / "f")]
    )
    return out, tmp


@pytest.fixture(scope="module")
def corrected(tmp_path_factory):
    return _corrected_fit(str(tmp_path_factory.mktemp("corrected")))


def test_the_corrected_model_refits_the_learned_term_with_a_b_c_mu(corrected):
    """fit --with-diagnosis of a diagnosis whose finding is a learned term: the term is
    refitted in the whole chain with every parameter (its coefficient against the planted
    damper), a, b, c, mu against the rig's truth."""
    out, tmp = corrected
    assert out.exit_code == 0, out.output
    doc = json.loads((tmp / "f" / "fit.json").read_text())
    (term,) = doc["learned"]
    assert term["depends_on"] == ["x_rate"]
    coef = float(term["equation"].split("=")[1].split("·")[0])
    assert coef == pytest.approx(DAMPING_NS_PER_M, rel=0.05)
    for name in ("a", "b", "c", "mu"):
        true = getattr(rig.RigParams(), name)
        assert abs(doc["params"][name] - true) <= 3 * doc["stderr"][name], name
    assert "learned term at" in out.output and "dx/dt" in out.output


def test_the_corrected_model_validates_on_another_recording(corrected):
    """validate simulates the corrected model, learned term rebuilt on a recording it
    was not fitted to: the force it misses by 5x its noise without the term is at the
    noise floor with it."""
    from typer.testing import CliRunner

    from ewb_ident.cli import app

    out, tmp = corrected
    runner = CliRunner()
    ok = runner.invoke(
        app, ["validate", str(tmp / "b.csv"), "--params", str(tmp / "f" / "fit.json"),
              "--out", str(tmp / "v")],
    )  # fmt: skip
    assert ok.exit_code == 0, ok.output
    with_term = json.loads((tmp / "v" / "validate.json").read_text())
    (name,) = with_term["mechanisms"]
    assert name in ("learned[sensor.force_N]", "learned[force.output]")
    base = json.loads((tmp / "f" / "fit.json").read_text())
    base = {"params": base["baseline"]["params"], "converged": True}
    (tmp / "base.json").write_text(json.dumps(base))
    runner.invoke(
        app, ["validate", str(tmp / "b.csv"), "--params", str(tmp / "base.json"),
              "--out", str(tmp / "v0")],
    )  # fmt: skip
    without = json.loads((tmp / "v0" / "validate.json").read_text())
    assert without["metrics"]["force_N"]["noise_ratio"] > 3.0
    assert with_term["metrics"]["force_N"]["noise_ratio"] < 1.5


def test_a_learned_term_that_cannot_be_rebuilt_is_refused_in_one_line(corrected, tmp_path):
    """A broken basis, and a term depending on a signal the trace lacks: exit 2, one
    line naming the file or the signal, nothing written."""
    from typer.testing import CliRunner

    from ewb_ident.cli import app

    _, tmp = corrected

    def refused(edit) -> str:  # fit --with-diagnosis of the diagnosis with one edit
        doc = json.loads((tmp / "diagnosis.json").read_text())
        edit(doc["findings"][0]["basis"])
        (tmp_path / "diagnosis.json").write_text(json.dumps(doc))
        out = CliRunner().invoke(
            app, ["fit", str(tmp / "a.csv"), "--with-diagnosis", str(tmp_path),
                  "--out", str(tmp_path / "f")],
        )  # fmt: skip
        assert out.exit_code == 2, out.output
        assert len(out.output.strip().splitlines()) == 1 and not (tmp_path / "f").exists()
        return out.output

    def nonsense_form(basis):
        basis["terms"][0][0]["form"] = ["nonsense", 1]

    assert "not a learned term's basis" in refused(nonsense_form)
    assert "current_mA, which is no channel" in refused(
        lambda basis: basis.update(raw_channels=["current_mA"])
    )
    fit = json.loads((tmp / "f" / "fit.json").read_text())
    fit["learned"][0]["basis"]["refs"] = {"disc_angle": 6.28}
    fit["learned"][0]["basis"]["terms"] = [[{"label": "sin(φ_d)", "signal": "disc_angle",
                                              "form": ["harm", 1, "sin"]}]]  # fmt: skip
    (tmp_path / "fit.json").write_text(json.dumps(fit))
    trace = damped_force_trace()
    ch = {k: v for k, v in trace.channels.items() if k != "disc_speed_rad_s"}
    from ewb_ident.data.writers import write_trace

    write_trace(dataclasses.replace(trace, channels=ch), tmp_path / "nodisc.csv")
    out = CliRunner().invoke(
        app, ["validate", str(tmp_path / "nodisc.csv"), "--params", str(tmp_path / "fit.json"),
              "--out", str(tmp_path / "v")],
    )  # fmt: skip
    assert out.exit_code == 2 and "disc_angle" in out.output, out.output
    assert not (tmp_path / "v").exists()


def test_a_learned_coefficients_posterior_does_not_depend_on_its_size():
    """The same damper term written with columns a million times larger (its coefficient
    a million times smaller): the posterior samples the coefficient in units of its
    distilled size with the same prior, so it still centres on the refitted term."""
    from ewb_ident.diagnosis.corrected import fit_corrected
    from ewb_ident.diagnosis.learned_spec import LearnedSpec
    from ewb_ident.inference.log_posterior import SamplerSettings
    from ewb_ident.inference.posterior import sample_corrected

    basis = json.loads(json_text(damped_diagnosis().findings[0].basis))
    basis["refs"] = {k: v * 1e-6 for k, v in basis["refs"].items()}
    basis["coef"] = [c * 1e-6 for c in basis["coef"]]
    spec = LearnedSpec.from_json(basis, "test")
    trace = damped_force_trace()
    cf = fit_corrected(trace, [], [spec])
    settings = SamplerSettings(n_steps=300, max_steps=300, seed=1)
    post = sample_corrected(trace, cf, settings=settings)
    (name,) = [n for n in post.names if n.startswith("learned[")]
    st = post.stats[name]
    assert st["hdi_low"] <= 1.0 <= st["hdi_high"] and st["hdi_high"] - st["hdi_low"] < 0.2


def test_a_place_whose_fit_cannot_be_linearised_learns_no_term(monkeypatch):
    """A fit whose Jacobian is not finite there (a switching mechanism at a corner) is no
    place to learn a term: discovery passes it over instead of failing the diagnosis."""
    from ewb_ident.diagnosis.session import Session
    from ewb_ident.inference import augmented

    ses = Session(damped_force_trace())
    ses.baseline()
    real = augmented.residuals_and_jacobian

    def not_finite(*args, **kwargs):
        r, J, rest = real(*args, **kwargs)
        return r, np.asarray(J) * np.nan, rest

    monkeypatch.setattr(augmented, "residuals_and_jacobian", not_finite)
    assert places.linearised(ses, ses.base_fits["force"], "force.output")[4] is None
    assert disc_mod.discover(ses, "force", lambda stages: ses.fit(stages, ())) is None


def test_the_motor_response_of_an_armature_far_faster_than_the_sample_is_finite():
    """An armature with L/R far below the sample step (||A dt|| in the thousands) has a
    fast response, not an overflowing one: the response equals the exponential map's
    for a usual armature, and tends to its L -> 0 limit for a tiny one."""
    from ewb_ident.model.integrate import zoh_map
    from ewb_ident.model.physics import motor_matrices

    values = {"R": 1.0, "L": 2e-3, "kb": 0.09, "kT": 0.1, "M": 2e-5, "v": 0.002}
    A, B_V, _ = motor_matrices(*values.values())
    F, g = (np.asarray(z, float) for z in zoh_map(A, B_V, 1e-3))
    h = places.motor_response(values, 1e-3, 200)
    # Sample 2's response to a unit voltage over sample 0 is F g (current, angle in deg).
    np.testing.assert_allclose(h[2, 0, 0], (F @ g)[0], rtol=1e-10)
    np.testing.assert_allclose(h[2, 1, 0], (F @ g)[2] * 180 / np.pi, rtol=1e-10)
    fast = places.motor_response(values | {"L": 3e-7}, 1e-3, 200)
    faster = places.motor_response(values | {"L": 3e-9}, 1e-3, 200)
    assert np.all(np.isfinite(fast))
    np.testing.assert_allclose(fast[1:], faster[1:], rtol=1e-2, atol=1e-3 * np.abs(faster).max())


def test_a_temperature_rise_that_cools_is_an_input_and_a_clipping_is_in_the_basis():
    """The squared current low-passed over each history time constant is an input (a
    thermal state with that time constant), and a signed input's learned basis holds
    the odd hinges sign(s) max(0, |s| - k) of a clipping or dead zone."""
    trace, run, _ = _clean()
    i = np.asarray(run.states["current_A"], float)
    sig = inputs.input_signals(trace, {"current_A": i})
    a = np.exp(-trace.dt / 0.5)
    lp = np.empty_like(i)
    acc = i[0] ** 2
    for k, v in enumerate(i**2):
        acc = a * acc + (1 - a) * v
        lp[k] = acc
    np.testing.assert_allclose(sig["heat_history_0.5s"].values, lp, rtol=1e-9, atol=1e-12)
    groups = inputs.learned_groups(sig)
    forms = [c.form for c in groups["current"]]
    assert ("ohinge", 1 / 3) in forms and ("ohinge", 2 / 3) in forms
    col = next(c for c in groups["current"] if c.form == ("ohinge", 2 / 3))
    ref = sig["current"].ref
    np.testing.assert_allclose(
        col.values, np.sign(i) * np.maximum(np.abs(i) / ref - 2 / 3, 0.0), atol=1e-12
    )
    assert col.label.startswith("sign(i)·max(0, |i| − ")


def test_a_signed_carriers_sign_times_another_signal_is_in_the_basis_and_reads_so():
    """A friction whose size another signal sets opposes the motion with the size of
    that signal: the motor speed's sign times the force (and times a harmonic of the
    angle, a shaft that binds once per turn) is in the learned basis and the library,
    and its equation reads ``sign(ω)·F`` in N·m per N."""
    trace, run, _ = _clean()
    sig = inputs.input_signals(trace, {})
    w, F = sig["speed"], sig["force"]
    groups = inputs.learned_groups(sig, ("speed", "force"), {"angle": [360.0]})
    col = next(c for c in groups["speed*force"] if c.form == ("sprod", "speed", "force"))
    np.testing.assert_allclose(col.values, np.tanh(w.values / (0.05 * w.ref)) * F.values / F.ref)
    assert col.label == "sign(ω)·F"
    assert inputs.physical(col, sig) == ("sign(ω)·F", 1 / F.ref, "N")
    assert inputs.render(col, 0.5 * F.ref, sig) == "+0.5·sign(ω)·F"
    trig = [c.label for c in groups["speed*angle@360"]]
    assert "sign(ω)·cos(2πθ/360°)" in trig and "ω·cos(2πθ/360°)" in trig
    assert len(groups["force*x"]) == 2  # a carrier that is not signed: F·x, F·x²
    items = inputs.library(sig, ["speed*force"])
    assert [c.form for (c,) in items].count(("sprod", "speed", "force")) == 1
    # a term the refit through the model set to nothing is left out of the equation
    force = next(c for c in groups["force"] if c.label == "F")
    eq = disc_mod.equation_of("motor.mechanical", [[col], [force]], [0.5 * F.ref, 1e-15], sig)
    assert "sign(ω)·F" in eq and "·F [" not in eq.replace("sign(ω)·F", "")
    both = disc_mod.equation_of("motor.mechanical", [[col], [force]], [0.5, 0.5], sig)
    assert both.count("·F") == 2


def test_the_filters_equal_scipy_signals():
    """The low-pass and the convolution discovery computes without importing
    scipy.signal give SciPy's numbers (signed zeros, layouts, many lengths), to rounding:
    they do SciPy's operations in its order (bit for bit with the SciPy they were written
    against), so a diagnosis is the same as with SciPy's own."""
    from scipy.signal import fftconvolve, lfilter

    from ewb_ident.diagnosis.filters import fft_convolve_columns, first_order_lowpass

    def same(got, ref):
        assert got.dtype == ref.dtype and got.shape == ref.shape
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())

    rng = np.random.default_rng(3)
    for trial in range(200):
        n = int(rng.integers(1, 1500))
        y = rng.normal(size=n) * 10.0 ** int(rng.integers(-6, 6))
        if trial % 2:
            y[rng.random(n) < 0.3] = 0.0
            y[rng.random(n) < 0.1] *= -0.0
        a = float(np.exp(-float(rng.choice([1e-3, 5e-3])) / float(rng.choice([0.1, 2.0, 1e-4]))))
        same(
            first_order_lowpass(y, 1.0 - a, a, a * y[0]),
            lfilter([1.0 - a], [1.0, -a], y, zi=[a * y[0]])[0],
        )
        m, k = int(rng.integers(2, 1500)), int(rng.integers(1, 6))
        h = rng.normal(size=(m, 2, 2))
        U = rng.normal(size=(m, k))
        U = np.asfortranarray(U) if trial % 3 else U
        same(fft_convolve_columns(h[:, 1, 0], U), fftconvolve(h[:, 1, 0][:, None], U, axes=0))


def test_average_ranks_equal_scipys_rankdata():
    """The ranks discovery computes without importing scipy.stats (about 1 s at every
    diagnose) are SciPy's: ties share the mean of their ranks, on many lengths and tie
    patterns."""
    from scipy.stats import rankdata

    rng = np.random.default_rng(5)
    for trial in range(200):
        n = int(rng.integers(1, 400))
        v = rng.normal(size=n)
        if trial % 2:
            v = np.round(v * float(rng.choice([1.0, 3.0, 10.0])))  # many ties
        np.testing.assert_array_equal(filters.average_ranks(v), rankdata(v))


@pytest.mark.slow
def test_an_armature_that_heats_and_cools_is_learned_on_its_thermal_state(tmp_path):
    """Armature heating on an independent rig, R = R0 (1 + h) with h the squared current
    through a 0.5 s thermal lag (no catalog mechanism). Where the current sensor reads the
    current well above its noise (500 Hz, RMS 12x the noise), the learned term acts in the
    motor's electrical equation, depends on the current times the squared current
    low-passed with the planted time constant, and generalises. Where the current is at
    its noise level (100 Hz, RMS 1.4x), a resistance that rises and a torque constant that
    falls move the angle alike: either motor equation may carry the term, and the finding
    says that the other explains it about as well."""
    from ewb_ident.data.readers import read_trace
    from validation_rigs import uncatalogued_rig as ur

    for seed, idx, told in ((9, 8, True), (7, 2, False)):
        case = ur.make_case("armature_heating", "a", seed, idx)
        assert case.truth["params"]["effect"]["tau_th"] == 0.5 and case.truth["has_current"]
        res = diagnose(read_trace(ur.write_case(case, tmp_path, f"heating{seed}")))
        (top,) = [f for f in res.findings if f.place]
        assert set(top.depends_on) == {"current", "heat_history_0.5s"}
        assert top.heldout["excess_share"] >= 0.5
        if told:
            assert top.place == "motor.electrical"
        else:
            assert top.place in ("motor.electrical", "motor.mechanical")
            other = ({"motor.electrical", "motor.mechanical"} - {top.place}).pop()
            assert f"{other} (on" in top.explanation and "the trace cannot tell" in top.explanation


@pytest.mark.slow
def test_a_catalog_name_beside_a_learned_term_must_also_win_on_heldout_data(tmp_path):
    """A supply sag on an independent rig (500 Hz, no current sensor, 57x the noise):
    `current_limit` with a learned term on top beat the learned term alone by dBIC -11.5
    in the fit, but left 1.5 times its held-out residual. The finding is the learned term
    alone, in the motor's voltage, on the current the sag depends on. (Since the learned
    terms' evidence is counted with the held-out folds' cap on the lag-1 correlation, a
    term alone that the pair no longer beats in BIC drops the name first; the held-out
    branch is tested on its own in ``test_diagnose.py``. Since a signed carrier's sign
    multiplies other inputs, the distilled term is ``sign(i)`` times the angle travelled
    since a reversal, held-out share 0.94 against 0.89 for a function of the current
    alone: without a current sensor the model's current lacks the sag, and a proxy can
    predict better. The current is still its first input.)"""
    from ewb_ident.data.readers import read_trace
    from validation_rigs import uncatalogued_rig as ur

    case = ur.make_case("supply_sag", "b", 20261362, 5)
    res = diagnose(read_trace(ur.write_case(case, tmp_path, "sag")))
    assert not any(f.catalog for f in res.findings)
    (top,) = [f for f in res.findings if f.place]
    assert top.place == "motor.electrical" and top.depends_on[0] == "current"
    assert top.heldout["excess_share"] >= 0.5
    why = "current_limit: not reported: a learned term at motor.electrical alone "
    assert any(n.startswith(why) for n in res.notes)
    # The sag leaves a, b, c unresolved (a ± 0.14 m): the diagnosis says so.
    assert any(n.startswith("the corrected a, b, c are not pinned down") for n in res.notes)


@pytest.mark.slow
def test_a_catalog_name_beside_a_term_at_other_stages_is_weighed_on_the_stages_of_either(
    tmp_path,
):
    """A preloaded return spring on the third probe (500 Hz staircase, no current sensor):
    `wedge_load_torque` with a learned term on top against the learned term alone,
    which acts on the motor's load torque. Where the term on top acted at the angle
    sensor (the motor and gap stages) the two were never compared; now they are, on the
    stages of either when they differ, and the notes say what the name was weighed
    against and how it came out (the name is dropped, or kept with the evidence for the
    pair; the spring is no wedge load torque, so a better term alone would drop it:
    either outcome passes)."""
    import re

    from ewb_ident.data.readers import read_trace
    from validation_rigs import probe3_rig
    from validation_rigs import uncatalogued_rig as ur

    case = probe3_rig.make_case("return_spring", "a", 20261368, 12)
    res = diagnose(read_trace(ur.write_case(case, tmp_path, "spring")))
    (note,) = [n for n in res.notes if n.startswith("wedge_load_torque: ") and " alone " in n]
    gain = float(re.search(r"dBIC ([-+0-9.]+)", note).group(1))
    kept = "wedge_load_torque" in [f.effect for f in res.findings if f.catalog]
    assert kept == ("kept beside the learned term at" in note)
    assert (gain <= -10) == kept


@pytest.mark.slow
def test_a_catalog_name_is_weighed_on_the_stages_of_either_when_the_term_alone_acts_elsewhere(
    tmp_path,
):
    """A preloaded return spring on the third probe (1 kHz PI loop, no current sensor):
    `wedge_load_torque` and `stiction` with a learned motor load torque on top, where the
    learned term alone acts at the angle sensor (the motor and gap stages). The two are
    fitted on the stages of either and compared in BIC; the note says so, and the names
    it keeps are the findings' (dBIC of the pair at or under the threshold)."""
    import re

    from ewb_ident.data.readers import read_trace
    from validation_rigs import probe3_rig
    from validation_rigs import uncatalogued_rig as ur

    case = probe3_rig.make_case("return_spring", "a", 20261377, 0)
    res = diagnose(read_trace(ur.write_case(case, tmp_path, "spring")))
    either = [n for n in res.notes if n.endswith("(on the stages of either)")]
    assert either
    named = {f.effect for f in res.findings if f.catalog}
    for note in either:
        names = note.split(":")[0].split(", ")
        gain = float(re.search(r"dBIC ([-+0-9.]+)", note).group(1))
        assert (": kept beside" in note) == (set(names) <= named)
        assert (gain <= -10) == (": kept beside" in note)


@pytest.mark.slow
def test_a_larger_gain_that_fails_a_heldout_fold_does_not_hide_a_term_that_generalises(
    tmp_path,
):
    """A quadratic drag on the motor of an independent rig, 100 Hz, no current sensor:
    the angle sensor's term (on the stages of the motor and the gap together, far worse
    fitted without it) removes more residual in absolute terms but fails one of the
    three applies held out, while the motor's term on the speed removes all but the noise
    in every fold. The verdict was `unexplained` with no term while the place first by
    gain was kept whatever its distilled term did on held-out data (and the sensor's
    input was then listed as a signal the trace cannot tell from the speed)."""
    from ewb_ident.data.readers import read_trace
    from validation_rigs import uncatalogued_rig as ur

    case = ur.make_case("quadratic_drag", "a", 20261357, 38)
    assert not case.truth["has_current"] and case.truth["rate"] == 100
    res = diagnose(read_trace(ur.write_case(case, tmp_path, "drag")))
    (top,) = [f for f in res.findings if f.place]
    assert top.place.startswith("motor.") and top.depends_on == ("speed",)
    assert top.heldout["excess_share"] >= 0.8
    # The sensor's term failed the folds: its input is no twin of the speed.
    assert "current" not in top.equivalents


@pytest.mark.slow
def test_a_drag_is_learned_on_the_speed_not_on_the_logged_voltage(tmp_path):
    """A quadratic drag on the motor of an independent rig, 1 kHz, closed loop: a term on
    the logged voltage (recorded exactly) fits held-out data about as well as one on the
    speed the model computes about the biased baseline; the voltage is the drive, not a
    state of the circuit, and the drag was learned on it with the speed as its twin."""
    from ewb_ident.data.readers import read_trace
    from validation_rigs import uncatalogued_rig as ur

    case = ur.make_case("quadratic_drag", "b", 20261359, 39)
    assert case.truth["rate"] == 1000 and case.truth["depends_on"] == ["speed"]
    res = diagnose(read_trace(ur.write_case(case, tmp_path, "drag")))
    (top,) = [f for f in res.findings if f.place]
    assert top.place.startswith("motor.") and top.depends_on == ("speed",)
    assert top.heldout["excess_share"] >= 0.8


@pytest.mark.slow
def test_a_drag_that_builds_over_a_stroke_and_outlasts_it_is_learned_on_the_speeds_history(
    tmp_path,
):
    """A viscoelastic gear grease (an independent rig's, 500 Hz, closed loop): its drag
    follows the motor speed through a relaxation, so the term is learned on the speed
    low-passed over a time constant, at the motor, with no catalog name."""
    from ewb_ident.data.readers import read_trace
    from validation_rigs import probe7_rig
    from validation_rigs import uncatalogued_rig as ur

    case = probe7_rig.make_case("grease_viscoelastic_drag", "a", 20261397, 14)
    res = diagnose(read_trace(ur.write_case(case, tmp_path, "grease")))
    assert not any(f.catalog for f in res.findings)
    (top,) = [f for f in res.findings if f.place]
    assert top.place.startswith("motor.") and top.depends_on[0].startswith("speed_history_")
    assert top.heldout["excess_share"] >= 0.8


@pytest.mark.slow
def test_an_lvdt_nonlinearity_is_learned_on_the_displacement_it_reads(tmp_path):
    """A displacement sensor whose reading bends with the displacement, on an
    independent rig (200 Hz, voltage steps): the term at the sensor fitted held-out data
    a little better on the recorded angle than on the displacement, which is the gap
    curve of that angle, and was reported as depending on the angle. The trace cannot
    tell the two apart; the sensor reads the displacement."""
    from ewb_ident.data.readers import read_trace
    from validation_rigs import uncatalogued_rig as ur

    case = ur.make_case("lvdt_nonlinearity", "a", 20261360, 26)
    assert case.truth["place"] == "sensor.x_m" and case.truth["depends_on"] == ["x"]
    res = diagnose(read_trace(ur.write_case(case, tmp_path, "lvdt")))
    (top,) = [f for f in res.findings if f.place]
    assert top.place == "sensor.x_m" and top.depends_on == ("x",)
    assert "angle" in top.equivalents
    assert top.heldout["excess_share"] >= 0.8


@pytest.mark.slow
def test_a_learned_term_that_the_chain_absorbed_is_confirmed_from_a_consistent_start(tmp_path):
    """A quadratic drag on the motor of an independent rig, no current sensor: the chain
    fitted from the voltage without the term has bent a, b, c to take it up, so the
    chain's fit with the term must also start from its stage's fit with it and from its
    coefficients at zero; from the bent values with the term added it ended worse than
    without (dBIC +198), the term was not reported and a, b, c came out 25 % low."""
    from ewb_ident.data.readers import read_trace
    from validation_rigs import uncatalogued_rig as ur

    case = ur.make_case("quadratic_drag", "a", 20261330, 10)
    assert not case.truth["has_current"]
    res = diagnose(read_trace(ur.write_case(case, tmp_path, "drag")))
    (top,) = [f for f in res.findings if f.place]
    assert top.place.startswith("motor.")
    assert top.heldout["excess_share"] >= 0.8
    rig_p = case.truth["params"]["rig"]
    for k in ("a", "b", "c"):
        est, se = res.augmented_params[k], res.augmented_stderr[k]
        assert abs(est - rig_p[k]) <= 1.645 * se and abs(est / rig_p[k] - 1) < 0.03


def test_a_sensor_term_takes_no_input_computed_from_the_channel_it_explains():
    """A term at the force sensor shows in the force stage and the torque stage it feeds;
    the torque among its inputs is the model's brake torque of the model's force, not of
    the recorded force, which carries the very mismatch (a damper here) the term is to
    explain: the input would reconstruct the residual."""
    from ewb_ident.diagnosis.session import Session, model_channels
    from ewb_ident.model.physics import brake_torque

    trace = damped_force_trace()
    ses = Session(trace)
    ses.baseline()
    fit = ses.fit(("force", "torque"), ())
    model = model_channels(ses, fit)
    mu = fit.values["mu"]
    from_model = np.asarray(brake_torque(model["force_N"], mu, trace.r_eff_m))
    np.testing.assert_allclose(model["torque_Nm"], from_model, rtol=1e-12)
    recorded = np.asarray(brake_torque(trace["force_N"], mu, trace.r_eff_m))
    _, run, _ = _clean()
    damper = 2 * mu * trace.r_eff_m * DAMPING_NS_PER_M * np.gradient(run.states["x_m"], trace.dt)
    assert np.std(recorded - model["torque_Nm"]) > 0.5 * np.std(damper)


CROSSTALK_NM_PER_A = 15.0  # a torque reading that picks up the motor current


def test_a_sensor_picking_up_a_fast_signal_takes_it_at_its_own_sample():
    """At 100 Hz the motor current's transients after each voltage step are shorter than
    a sample. A torque reading that picks up the current, ``T + k i``, is explained by
    the current at the same sample: a recorded channel whose noise is not in the
    torque's residual enters as recorded, not as its neighbours' average (which misses
    the transient and gave ``k tanh(i / i0)``, two thirds of the gain)."""
    noise = rig.SensorNoise()
    settings = SETTINGS | dict(sample_rate_hz=100.0, seed=9, profile="steps")
    trace, _, run = rig.simulate_rig(rig.RigParams(), noise=noise, return_clean=True, **settings)
    truth = CROSSTALK_NM_PER_A * run.states["current_A"]
    rng = np.random.default_rng(23)
    ch = dict(trace.channels)
    ch["torque_Nm"] = (
        run.states["torque_Nm"] + truth + noise.sigma("torque_Nm") * rng.standard_normal(trace.n)
    )
    trace = dataclasses.replace(trace, channels=ch, name="crosstalk")
    res = diagnose(trace)
    (top,) = res.findings
    assert top.place in ("sensor.torque_Nm", "torque.output")
    assert top.depends_on == ("current",)
    (term,) = top.terms
    assert term["expression"] == "i"
    assert term["coef"] == pytest.approx(CROSSTALK_NM_PER_A, rel=0.05)
    assert np.sqrt(np.mean((top.term_series - truth) ** 2)) < 0.1 * np.sqrt(np.mean(truth**2))
    assert top.heldout["excess_share"] >= 0.8
    # The basis says which inputs were taken at their own sample, and the corrected
    # model rebuilds them so: refitted, the coefficient is the planted one again.
    from ewb_ident.diagnosis.corrected import fit_corrected
    from ewb_ident.diagnosis.learned_spec import LearnedSpec

    basis = json.loads(json_text(top.basis))
    assert "current_A" in basis["raw_channels"]
    cf = fit_corrected(trace, [], [LearnedSpec.from_json(basis, "crosstalk")])
    m = re.fullmatch(r"Δtorque_Nm = \+?([0-9.e+-]+)·i \[N\*m\]", cf.learned[0]["equation"])
    assert m, cf.learned[0]["equation"]
    assert float(m.group(1)) == pytest.approx(CROSSTALK_NM_PER_A, rel=0.05)


DRIFT_PER_S = 0.02  # a piezo washer's charge amplifier: the reading gains d * integral(F dt)


def test_a_force_reading_that_drifts_with_the_force_integral_is_learned_so():
    """A charge amplifier drifting with the charge it integrates: the force reading is
    ``F + d ∫F dt``. The drift lifts the open pads' reading into the force range, so the
    phases flicker into many "applies" of a few samples beside one holding most of the
    trace; held-out folds are then blocks in time (leaving that apply out would leave
    nothing to fit the bell on). The term is learned on the force's integral, with the
    planted coefficient, and no catalog offset is named for it."""
    trace, run, _ = _clean()
    F = run.states["force_N"]
    truth = DRIFT_PER_S * np.concatenate([[0.0], np.cumsum(0.5 * (F[1:] + F[:-1]))]) * trace.dt
    res = diagnose(_with({"force_N": F + truth}, "drift"))
    assert res.verdict == "unexplained" and not any(f.catalog for f in res.findings)
    (top,) = res.findings
    assert top.place == "sensor.force_N" and top.depends_on == ("force_integral",)
    (term,) = top.terms
    assert term["expression"] == "∫Fdt"
    assert term["coef"] == pytest.approx(DRIFT_PER_S, rel=0.05)
    assert np.sqrt(np.mean((top.term_series - truth) ** 2)) < 0.05 * np.sqrt(np.mean(truth**2))
    assert top.heldout["method"].startswith("4-fold blocked")
    assert top.heldout["excess_share"] >= 0.8


SET_PER_N = 0.02  # a load cell taking a set: its zero shifts with the largest load so far


def test_a_change_that_grows_at_each_new_force_record_is_learned_on_the_force_peak():
    """Physics that changes for good only when the load sets a new record (a pad bedding
    in, a plastic set; here a load cell whose zero shifts with its largest load): the
    largest force so far is an input, and the term is learned on it with the planted
    coefficient (a low-passed force fitted it only with a seven-per-cent error)."""
    trace, run, _ = _clean()
    F = np.asarray(run.states["force_N"])
    truth = SET_PER_N * np.maximum.accumulate(F)
    res = diagnose(_with({"force_N": F + truth}, "set"))
    assert res.verdict == "unexplained" and not any(f.catalog for f in res.findings)
    (top,) = res.findings
    assert top.place == "sensor.force_N" and top.depends_on == ("force_peak",)
    (term,) = top.terms
    assert term["coef"] == pytest.approx(SET_PER_N, rel=0.05)
    assert np.sqrt(np.mean((top.term_series - truth) ** 2)) < 0.02 * np.sqrt(np.mean(truth**2))
    assert "new record" in top.reading


def test_folds_leave_out_whole_applies_only_when_none_holds_most_of_the_trace():
    apply = ["gapping"] * 20 + ["clamping"] * 30 + ["release"] * 10
    idx, method = heldout.folds(np.array(apply * 3 + ["gapping"] * 20))
    assert method == "leave-one-apply-out over 3 applies" and idx.max() == 2
    flicker = ["gapping"] * 20 + ["saturation"] * 150 + (["gapping", "saturation"] * 4) * 3
    idx, method = heldout.folds(np.array(flicker))
    assert method == "4-fold blocked cross-validation in time"
    assert np.bincount(idx).min() >= len(flicker) // 4 - 1


LEAK_A_PER_V = 0.1  # a current reading that also takes a path across the motor's terminals


def _sensor_learned(channel: str, error, settings: dict, seed: int):
    """The one finding, uncatalogued, of a trace whose ``channel`` reads its true value
    plus ``error(trace, true values)`` and noise; and that error."""
    noise = rig.SensorNoise()
    trace, _, run = rig.simulate_rig(rig.RigParams(), noise=noise, return_clean=True, **settings)
    truth = error(trace, run.states[channel])
    rng = np.random.default_rng(seed)
    ch = dict(trace.channels)
    ch[channel] = run.states[channel] + truth + noise.sigma(channel) * rng.standard_normal(trace.n)
    res = diagnose(dataclasses.replace(trace, channels=ch, name=channel))
    assert not any(f.catalog for f in res.findings)
    (top,) = res.findings
    return top, truth


def test_a_current_reading_that_picks_up_the_voltage_is_learned_at_the_current_sensor():
    """The current sensor sits in the motor's circuit: a snubber or the driver's own
    supply current across the terminals adds ``V / R_p`` to its reading. Its term may
    depend on the voltage (no other sensor's may), and on a 1 kHz trace of voltage steps
    it is learned there, with the planted conductance."""
    settings = SETTINGS | dict(sample_rate_hz=1000.0, seed=9, profile="steps")
    top, truth = _sensor_learned(
        "current_A", lambda tr, _: LEAK_A_PER_V * tr["voltage_V"], settings, 31
    )
    assert top.place == "sensor.current_A" and top.depends_on == ("voltage",)
    (term,) = top.terms
    assert term["expression"] == "V"
    assert term["coef"] == pytest.approx(LEAK_A_PER_V, rel=0.1)
    assert np.sqrt(np.mean((top.term_series - truth) ** 2)) < 0.15 * np.sqrt(np.mean(truth**2))
    assert top.heldout["excess_share"] >= 0.8


HYST_WIDTH = 0.3  # a Hall sensor's core: a play of this share of the largest current
HYST_GAIN = 0.1  # ... whose lag behind the current adds this share of it to the reading


def test_the_current_and_the_force_each_have_their_change_since_they_last_reversed():
    """A hysteresis in a signal's own history (a play of the current in a Hall sensor's
    core, of the force in a load cell) needs that history as an input: the signal less
    its value at its last reversal, as the angle has (``travel``)."""
    from ewb_ident.diagnosis.filters import reversals
    from ewb_ident.diagnosis.inputs import REVERSAL_SHARE, input_signals

    trace, _, _ = _clean()
    sig = input_signals(trace, {})
    for name in ("current", "force"):
        moved = sig[f"{name}_travel"]
        expected = reversals(sig[name].values, REVERSAL_SHARE)[1]
        np.testing.assert_allclose(moved.values, expected)
        assert moved.kind == "signed" and moved.unit == sig[name].unit
        assert reversals(sig[name].values, REVERSAL_SHARE)[0].max() >= 1  # it does reverse


@pytest.mark.slow
def test_a_current_reading_with_magnetic_hysteresis_is_learned_on_the_current_reversals():
    """A Hall sensor whose core lags the current by a play (a rate-independent hysteresis
    of width ``r``: the reading gains ``g (i - play_r(i))``, which restarts at each
    reversal of the current and saturates at ``± g r``). It is in no catalog and depends
    on no signal but the current's own history: the term is learned at the current sensor
    on the current's change since it last reversed, follows the planted lag, and
    generalises."""

    def hysteresis(_, i):
        r, y, out = HYST_WIDTH * float(np.max(np.abs(i))), 0.0, np.empty(i.size)
        for k, v in enumerate(np.asarray(i, float)):
            y = min(max(y, v - r), v + r)
            out[k] = v - y
        return HYST_GAIN * out

    settings = SETTINGS | dict(sample_rate_hz=1000.0, seed=9, profile="steps")
    top, truth = _sensor_learned("current_A", hysteresis, settings, 41)
    assert top.place == "sensor.current_A" and "current_travel" in top.depends_on
    assert np.sqrt(np.mean((top.term_series - truth) ** 2)) < 0.3 * np.sqrt(np.mean(truth**2))
    assert top.heldout["excess_share"] >= 0.5
    assert "hysteresis" in top.reading


def test_reversals_count_from_each_extreme_and_ignore_a_dither_at_rest():
    from ewb_ident.diagnosis.filters import reversals

    t = np.arange(0.0, 2.0, 1e-3)
    y = 100.0 * np.sin(2 * np.pi * t) + 0.2 * np.sin(2 * np.pi * 40.0 * t)  # a 0.2 deg dither
    count, travel = reversals(y, 0.01)
    peaks = np.flatnonzero(np.diff(count)) + 1  # where each count starts
    assert count[-1] == 4 and count[0] == 0  # the four extremes of two periods
    assert np.all(np.abs(np.abs(y[peaks - 1]) - np.max(np.abs(y))) < 0.5)  # at the extremes
    assert travel[0] == 0 and travel[peaks[0]] == pytest.approx(y[peaks[0]] - y[peaks[0] - 1])
    rest = np.concatenate([np.linspace(0, 50, 200), 50 + 0.2 * np.sin(np.arange(400.0))])
    assert reversals(rest, 0.01)[0].max() == 0  # a dither at rest under 1 % of the range


SLIP_DEG = 0.3  # an encoder coupling that slips at each reversal of the motion


def test_an_encoder_that_slips_at_each_reversal_is_learned_on_the_reversal_count():
    """The angle reading loses ``SLIP_DEG`` at every reversal of the motion (its
    coupling slips): a sensor term that steps at events, not a function of any level.
    On a staircase with eleven reversals it is learned at the angle sensor on the count
    of reversals, with the planted step, and no catalog mechanism is named."""
    from ewb_ident.diagnosis.filters import reversals

    def slip(_, th):
        return -SLIP_DEG * reversals(th, 0.01)[0]

    top, _ = _sensor_learned("theta_deg", slip, SETTINGS | dict(profile="staircase"), 17)
    assert top.place == "sensor.theta_deg" and top.depends_on == ("reversals",)
    (term,) = top.terms
    assert term["expression"] == "n_rev"
    assert term["coef"] == pytest.approx(-SLIP_DEG, rel=0.05)
    assert "slipping" in top.reading
    assert top.heldout["excess_share"] >= 0.8


def test_the_denoised_level_is_closer_to_the_truth_than_a_fixed_window():
    """A channel's level without its noise at each sample: the leave-one-out average
    whose width predicts the samples best, which widens with the noise and never takes
    the sample's own noise."""
    t = np.arange(0.0, 3.0, 1e-3)
    true = 1000.0 * np.clip(np.sin(2 * np.pi * 0.7 * t), 0, None) ** 2
    rng = np.random.default_rng(3)
    for sigma in (5.0, 40.0):
        y = true + sigma * rng.standard_normal(t.size)
        best = filters.denoised(y, 1e-3)
        fixed = filters.leave_one_out(y, 5)
        assert np.sqrt(np.mean((best - true) ** 2)) < np.sqrt(np.mean((fixed - true) ** 2))
    y[1000] += 1e4  # one sample's noise is not in its own level
    assert abs(filters.denoised(y, 1e-3)[1000] - true[1000]) < 100.0


def test_a_friction_law_in_the_force_is_learned_on_the_force_when_its_reading_is_noisy():
    """mu falls with the clamping force, and the load cell is three times noisier than
    the torque sensor reads it (a 1 kHz trace of voltage steps). The friction term's
    change is the torque of the recorded force: scaled by the recorded force itself, it
    would carry the force's noise at each sample, which the torque stage's residual
    carries too, and a term on the quieter angle fitted that noise's attenuation on
    held-out data as well. It is learned on the force, with the planted slope."""
    settings = SETTINGS | dict(sample_rate_hz=1000.0, seed=12, profile="steps")
    noise = rig.SensorNoise()
    trace, _, run = rig.simulate_rig(rig.RigParams(), noise=noise, return_clean=True, **settings)
    rng = np.random.default_rng(23)
    F = run.states["force_N"]
    ch = dict(trace.channels)
    ch["force_N"] = F + 3 * noise.sigma("force_N") * rng.standard_normal(trace.n)
    T = run.states["torque_Nm"] * (1 - PRESSURE_K * F / 3500.0)
    ch["torque_Nm"] = T + noise.sigma("torque_Nm") * rng.standard_normal(trace.n)
    res = diagnose(dataclasses.replace(trace, channels=ch, name="mu_F_noisy"))
    assert not any(f.catalog for f in res.findings)
    (top,) = res.findings
    assert top.place == "friction" and top.depends_on == ("force",)
    (term,) = top.terms
    assert term["expression"] == "F"
    assert term["coef"] == pytest.approx(-PRESSURE_K / 3500.0, rel=0.25)
