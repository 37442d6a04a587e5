"""Least squares: recovery of known truth from the independent synthetic rig."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from ewb_ident import rig
from ewb_ident.data.outputs import json_text
from ewb_ident.data.readers import read_trace
from ewb_ident.data.trace import TraceError
from ewb_ident.inference.least_squares import fit
from ewb_ident.inference.problem import FitError

DATA = Path(__file__).parents[1] / "datasets"


def _truth(name):
    return json.loads((DATA / f"{name}.truth.json").read_text())["params"]


def _within(result, truth, names, n_se=4.0, rel=None, key=None):
    for name in names:
        est = result.values[name]
        se = result.stderr[key(name) if key else name]
        assert se is not None and se > 0, name
        assert abs(est - truth[name]) < n_se * se, (name, est, truth[name], se)
        if rel is not None:
            assert abs(est / truth[name] - 1) < rel, (name, est, truth[name])


@pytest.fixture(scope="module")
def staircase():
    return read_trace(DATA / "staircase_200hz.csv"), _truth("staircase_200hz")


@pytest.mark.parametrize(
    ("stage", "names", "rel"),
    [
        ("gap", ["p2", "p1", "p0"], 0.01),
        ("force", ["F_rt", "a", "b", "c"], 0.03),
        ("torque", ["mu"], 0.002),
    ],
)
def test_stagewise_teacher_forced_recovery(staircase, stage, names, rel):
    trace, truth = staircase
    result = fit(trace, stage=stage)
    assert result.converged, result.message
    _within(result, truth, names, rel=rel)
    ch = {"gap": "x_m", "force": "force_N", "torque": "torque_Nm"}[stage]
    # Fits to the noise. Teacher-forced stages also see their input sensor's noise: the
    # torque stage 2 mu r_eff * 10 N on top of 1 N*m; the force stage the bell's slope
    # (up to ~7 N/um) times 2 um of x noise.
    noise = {"x_m": 2e-6, "force_N": 10.0, "torque_Nm": np.hypot(1.0, 2 * 0.377 * 0.15 * 10)}
    high = 1.5 if stage == "force" else 1.15
    assert 0.85 * noise[ch] < result.metrics[ch]["rmse"] < high * noise[ch]


def test_motor_stage_recovers_identifiable_combinations(staircase):
    """Only ratios to kT are identified (no load-torque sensor); kT stays fixed at 0.1."""
    trace, truth = staircase
    result = fit(trace, stage="motor")
    assert result.converged
    assert result.free == ("R", "L", "kb", "M", "v", "theta0_deg")  # current: R, L too
    kT_fit = result.values["kT"]
    for name in ("M", "v"):
        ratio_fit, ratio_true = result.values[name] / kT_fit, truth[name] / truth["kT"]
        se = result.stderr[name] / kT_fit
        assert abs(ratio_fit - ratio_true) < 4 * se, name
    _within(result, truth, ["R", "kb"], rel=0.01)
    _within(result, truth, ["L"], rel=0.05)


def test_whole_chain_recovers_truth_when_the_piston_passes_c():
    trace, truth = read_trace(DATA / "through_c_500hz.csv"), _truth("through_c_500hz")
    result = fit(trace)
    assert result.converged, result.message
    _within(result, truth, ["F_rt", "a", "b", "c", "mu", "p2", "p1", "p0", "kb"], rel=0.02)
    assert not any("never passes" in w for w in result.warnings)
    for ch, m in result.metrics.items():
        assert m["nrmse_pct"] < 1.5, ch  # to the noise: far inside the seed's 3.3 %


def test_flank_only_trace_says_a_b_c_trade_off():
    trace = read_trace(DATA / "seed_steps_100hz.csv")
    result = fit(trace)
    assert result.converged
    assert any(
        "never passes the bell's centre c" in w and "trade off" in w for w in result.warnings
    )
    # the Jacobian sees it too: a and c move together
    i, j = result.corr_names.index("a"), result.corr_names.index("c")
    assert result.corr[i, j] > 0.95


def test_several_traces_share_parameters_and_keep_per_trace_ones():
    """A pad change moves the contact point: c fitted per trace, the rest shared."""
    base = rig.RigParams()
    new = dataclasses.replace(base, c=base.c + 50e-6)
    t_old, _ = rig.simulate_rig(base, profile="staircase", seed=11, name="old")
    t_new, _ = rig.simulate_rig(new, profile="staircase", seed=12, name="new")
    result = fit([t_old, t_new], stage="force", per_trace=["c"])
    assert result.converged
    c_old, c_new = (float(p.c) for p in result.params)
    se_old, se_new = result.stderr["c[0]"], result.stderr["c[1]"]
    assert abs(c_old - base.c) < 4 * se_old and abs(c_new - new.c) < 4 * se_new
    assert 30e-6 < c_new - c_old < 70e-6
    assert float(result.params[0].a) == float(result.params[1].a)  # shared
    doc = result.to_json()
    assert [pt["trace"] for pt in doc["per_trace"]] == ["old", "new"]
    assert set(doc["per_trace"][1]["params"]) == {"c"}


def test_poor_start_converges_or_says_it_did_not(staircase):
    trace, truth = staircase
    poor = {"a": 1.64e-3, "b": 7.9, "c": 2.02e-3}  # the SciPy solution from the issue
    result = fit(trace, stage="force", start=poor)
    assert result.converged, result.message
    _within(result, truth, ["a", "b", "c"], rel=0.05)
    stopped = fit(trace, stage="force", start=poor, max_steps=3)
    assert not stopped.converged
    assert "step limit (3)" in stopped.message
    assert stopped.to_json()["converged"] is False


def test_fixed_parameters_are_held_and_have_no_stderr(staircase):
    trace, _ = staircase
    result = fit(trace, stage="force", free=["a", "c"], fixed={"b": 3.0, "F_rt": 3600.0})
    assert result.values["b"] == 3.0 and result.values["F_rt"] == 3600.0
    doc = result.to_json()
    assert doc["stderr"]["b"] is None and doc["stderr"]["a"] is not None
    json.loads(json_text(doc))  # plain JSON, no NaN


def test_contract_keys_of_fit_json(staircase):
    trace, _ = staircase
    doc = json.loads(json_text(fit(trace, stage="torque").to_json()))
    assert {"params", "stderr", "metrics", "converged"} <= set(doc)
    assert {"a", "b", "c", "mu"} <= set(doc["params"])
    assert set(doc["metrics"]["torque_Nm"]) >= {"rmse", "nrmse_pct", "percent_error"}


def test_bad_requests_are_refused_with_a_message(staircase):
    trace, _ = staircase
    with pytest.raises(FitError, match="parameter 'mu' is not fitted by stage 'force'"):
        fit(trace, stage="force", free=["mu"])
    with pytest.raises(FitError, match="unknown stage 'brake'"):
        fit(trace, stage="brake")
    with pytest.raises(FitError, match="per-trace parameter 'c' must also be free"):
        fit(trace, stage="force", free=["a"], per_trace=["c"])
    no_torque = dataclasses.replace(
        trace, channels={k: v for k, v in trace.channels.items() if k != "torque_Nm"}
    )
    # The command line's words: the API checks its traces with the same function.
    with pytest.raises(TraceError, match="column 'torque_Nm'.*stage 'torque'.* needs it"):
        fit(no_torque, stage="torque")


def test_noise_levels_are_estimated_not_hand_set(staircase):
    trace, _ = staircase
    result = fit(trace, stage="torque")
    assert result.noise[0]["torque_Nm"] == pytest.approx(1.0, rel=0.15)
    # The fit weighs the torque sensor's own noise (re-estimated from the residual) and,
    # on top, the force sensor's carried through the input (2 mu r_eff * 10 N = 1.13 N m):
    # the residual holds both.
    assert result.sigma[0]["torque_Nm"] == pytest.approx(1.0, rel=0.1)
    assert result.metrics["torque_Nm"]["rmse"] == pytest.approx(np.hypot(1.0, 1.13), rel=0.1)
    assert np.isfinite(result.cost)


def test_a_diverging_seed_integrator_is_reported_not_raised():
    """Was: ``fit --integrator heun`` on the seed's own 100 Hz trace ended in a
    ``LinAlgError: SVD did not converge`` traceback (Heun at 0.01 s diverges for this
    armature, so the Jacobian held NaN). Now: not converged, no standard errors, and the
    words say why."""
    from ewb_ident.model.integrate import SEED_HEUN

    res = fit(read_trace(DATA / "seed_steps_100hz.csv"), integrator=SEED_HEUN, max_steps=20)
    assert not res.converged
    assert all(se is None for se in res.stderr.values())
    words = " ".join(res.warnings)
    assert "Heun's method at the seed's step is unstable" in words
    assert "not finite where the solver stopped" in words
    json.loads(json_text(res.to_json()))  # the contract's JSON is still written


def test_the_library_computes_in_float64_when_the_caller_did_not_ask():
    """One precision policy: a script that never turns on JAX's 64-bit mode gets the
    same fit, to the last digit, as the CLI (which does)."""
    import os
    import subprocess
    import sys

    code = (
        "import jax, ewb_ident as ei\n"
        "assert not jax.config.jax_enable_x64\n"
        f"r = ei.fit(ei.read_trace({str(DATA / 'steps_200hz.csv')!r}), stage='force')\n"
        "print(repr(r.values['a']), repr(r.values['c']))\n"
        "assert not jax.config.jax_enable_x64\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    here = fit(read_trace(DATA / "steps_200hz.csv"), stage="force")
    assert out.stdout.split() == [repr(here.values["a"]), repr(here.values["c"])]


# ----------------------------------------------------------------------------- serial errors


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.9])
def test_long_run_covariance_of_an_ar1_series(rho):
    from ewb_ident.inference.uncertainty import long_run_covariance

    rng = np.random.default_rng(1)
    n = 20000
    e = rng.standard_normal((n, 2))
    x = np.zeros_like(e)
    for t in range(1, n):
        x[t] = rho * x[t - 1] + e[t]
    # The long-run variance of an AR(1) with unit innovations is 1 / (1 - rho)^2.
    np.testing.assert_allclose(np.diag(long_run_covariance(x)) / n, 1 / (1 - rho) ** 2, rtol=0.15)


def test_serial_errors_do_not_depend_on_how_far_a_trace_is_padded():
    """A trace padded to a program's length ends in rows weighted zero; the robust
    variance is that of the recorded samples alone, whatever the padding."""
    from ewb_ident.inference.uncertainty import serial_variance

    rng = np.random.default_rng(4)
    n, nch, p = 601, 2, 3
    x = np.zeros((nch, n))
    e = rng.standard_normal((nch, n))
    for t in range(1, n):
        x[:, t] = 0.7 * x[:, t - 1] + e[:, t]
    J = rng.standard_normal((nch, n, p))
    inv = np.linalg.inv(np.einsum("cti,ctj->ij", J, J))
    want = serial_variance(J.reshape(-1, p), x.reshape(-1), inv, [(nch, n)])
    for n_pad in (640, 768, 4096):
        Jp = np.zeros((nch, n_pad, p))
        Jp[:, :n] = J
        rp = np.zeros((nch, n_pad))
        rp[:, :n] = x  # residual weighted zero beyond the record, as fits pad them
        got = serial_variance(Jp.reshape(-1, p), rp.reshape(-1), inv, [(nch, n_pad)])
        np.testing.assert_array_equal(got, want)


def test_one_function_gives_standard_errors_and_none_only_on_undetermined_directions():
    """``parameter_uncertainty`` is the one computation of standard errors (the augmented
    fits' own copy is gone). On a Jacobian with two proportional columns and one without
    slope, the three parameters on those undetermined directions get None and the other
    two keep the errors of the same fit with the duplicate and the flat column left out
    (the same residual variance, per degree of freedom)."""
    from ewb_ident.inference import augmented
    from ewb_ident.inference.uncertainty import parameter_uncertainty
    from ewb_ident.model.params import PARAMS

    assert not hasattr(augmented, "_stderr")
    assert not hasattr(augmented, "serial_sd")
    rng = np.random.default_rng(7)
    n = 500
    A = rng.standard_normal((n, 3))
    J = np.column_stack([A[:, 0], A[:, 1], -2.0 * A[:, 1], np.zeros(n), A[:, 2] + A[:, 0]])
    r = rng.standard_normal(n)
    u = np.linspace(-0.3, 0.4, 5)
    infos = [PARAMS[name] for name in ("R", "L", "kb", "M", "v")]
    for segments in (None, [(1, n)]):
        unc = parameter_uncertainty(J, r, u, infos, segments)
        for errors in (unc.stderr, unc.stderr_white):
            assert [e is None for e in errors] == [False, True, True, True, False]
        assert np.isinf(unc.sd_u[1:4]).all() and np.isfinite(unc.sd_u[[0, 4]]).all()
        assert unc.condition_number == float("inf")
    kept = [0, 1, 4]
    full = parameter_uncertainty(J, r, u, infos)
    part = parameter_uncertainty(J[:, kept], r, u[kept], [infos[k] for k in kept])
    dof = np.sqrt((n - len(kept)) / (n - len(infos)))  # the same rss over fewer dof
    for j, k in ((0, 0), (4, 2)):
        np.testing.assert_allclose(full.stderr[j], part.stderr[k] * dof, rtol=1e-9)
    # A determined Jacobian: every parameter has its error, as before.
    assert None not in parameter_uncertainty(A, r, u[:3], infos[:3], [(1, n)]).stderr


def test_z90_is_the_normal_quantile_of_the_interval_probability():
    from scipy.special import ndtri

    from ewb_ident.data.metrics import INTERVAL_PROB, Z90
    from ewb_ident.inference.log_posterior import SamplerSettings

    assert Z90 == float(ndtri(0.5 + INTERVAL_PROB / 2))
    assert SamplerSettings().hdi_prob == INTERVAL_PROB


def test_standard_errors_widen_where_the_model_leaves_physics_out():
    """White residuals: the robust errors are the white ones. A concealed hysteresis
    (the model leaves it out, the residual runs for hundreds of samples): the white
    90 % intervals of a, b, c miss the truth by 5-6 standard errors; the robust ones
    hold it."""
    p = rig.RigParams(disc_speed_end_rad_s=30.0)
    clean, _ = rig.simulate_rig(p, profile="position", seed=3)
    f = fit(clean)
    for n in ("a", "b", "c", "mu"):
        assert 1.0 <= f.stderr[n] / f.stderr_white[n] < 1.3
    hyst, _ = rig.simulate_rig(p, profile="position", seed=3, effects=[rig.ForceHysteresis(h=0.04)])
    f = fit(hyst)
    assert f.converged
    for n in ("a", "b", "c"):
        z_white = (f.values[n] - getattr(p, n)) / f.stderr_white[n]
        z = (f.values[n] - getattr(p, n)) / f.stderr[n]
        assert abs(z_white) > 3.0 and abs(z) < 1.645
    doc = f.to_json()
    assert doc["stderr_white"]["a"] == pytest.approx(f.stderr_white["a"])


def test_the_solver_reaches_the_optimum_optimistix_reaches(staircase):
    """The NumPy Levenberg-Marquardt around the compiled residuals and Jacobian stops
    where optimistix's solver (compiled whole; the seed fits' solver before) stops, to a
    small fraction of a standard error, at a cost no higher."""
    import optimistix as optx

    from ewb_ident.inference.log_posterior import info_of

    trace, _ = staircase
    result = fit(trace)
    assert result.converged
    problem, data = result.problem, result.data
    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12)
    ref = optx.least_squares(problem, solver, result.u, args=data, max_steps=300, throw=False)
    assert ref.result == optx.RESULTS.successful
    u_ref = np.asarray(ref.value)
    cost = float(np.sum(np.asarray(problem(result.u, data)) ** 2))
    cost_ref = float(np.sum(np.asarray(problem(u_ref, data)) ** 2))
    assert cost <= cost_ref * (1 + 1e-9)
    for j, name in enumerate(result.corr_names):
        se = result.stderr[name]
        slope = abs(float(info_of(name).dp_du(result.u[j])))
        assert abs(result.u[j] - u_ref[j]) * slope < 0.01 * se, name


def test_one_levenberg_marquardt_serves_every_fit():
    """One loop, named after its algorithm, solves the stage and chain fits and the fits
    with mechanisms (each with its own descent and stopping rule); the loop named after
    its caller is gone."""
    from ewb_ident.inference import augmented, least_squares, solvers

    assert least_squares.levenberg_marquardt is solvers.levenberg_marquardt
    assert augmented.levenberg_marquardt is solvers.levenberg_marquardt
    assert not hasattr(solvers, "seed_levenberg_marquardt")
    for path in Path(solvers.__file__).parents[1].rglob("*.py"):
        assert "seed_levenberg_marquardt" not in path.read_text(encoding="utf-8"), path


def test_one_problem_type_and_one_result_type():
    """The seed model's fits and the fits with mechanisms or learned terms share one
    problem type (``Problem``: ``specs`` empty for the seed model) and one result type
    (``FitResult``: ``mechanisms`` empty for the seed model); the retired names are gone
    from the package."""
    import ewb_ident
    from ewb_ident.inference import augmented, fit_result, problem

    assert ewb_ident.FitResult is fit_result.FitResult
    assert problem.Problem.__dataclass_fields__["specs"].default == ()
    for module in (ewb_ident, augmented, fit_result, problem):
        for name in ("AugProblem", "AugFit", "StageProblem"):
            assert not hasattr(module, name), (module.__name__, name)
    for path in Path(problem.__file__).parents[1].rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        for name in ("AugProblem", "AugFit", "StageProblem"):
            assert name not in text, (path, name)


@pytest.mark.parametrize("stage", ["motor", "gap", "force", "torque", "chain"])
def test_one_program_predicts_each_stage_as_the_chain_evaluator_does(staircase, stage):
    """The fits' single compiled program picks each stage's input by data; its
    predictions equal :func:`ewb_ident.model.predict.predict` of that stage."""
    import jax.numpy as jnp

    from ewb_ident.inference.problem import build_setup, to_u
    from ewb_ident.inference.residuals import evaluate
    from ewb_ident.model.integrate import EXPONENTIAL
    from ewb_ident.model.params import MODEL_PARAMS, EWBParams
    from ewb_ident.model.predict import predict

    trace, _ = staircase
    setup = build_setup(trace, stage, None, None, {}, EXPONENTIAL)
    u = np.asarray(to_u(setup.problem, {}, setup.base, setup.tdata)) + 0.01
    data = setup.data(setup.sensor_sigma())
    _, preds, _ = evaluate(setup.problem, u, data)
    vals = setup.problem.values(jnp.asarray(u), setup.base.as_dict() | {"theta0_deg": 0.0}, 0)
    p = EWBParams(**{n: vals[n] for n in MODEL_PARAMS})
    d = {"meas": data["traces"][0], "dt": data["traces"][0]["dt"], "r_eff": trace.r_eff_m}
    ref = predict(stage, p, vals["theta0_deg"], (), d, 1, "exponential")
    for ch in setup.channels[0]:
        np.testing.assert_allclose(preds[0][ch], np.asarray(ref[ch]), rtol=1e-12, atol=1e-12)


def test_force_stage_weighs_the_displacement_noise_it_carries():
    """Errors in variables: the bell read at a noisy displacement carries ``F' sigma_x``
    of noise, largest where the bell is steep. Weighed by the force sensor's noise alone,
    a least-squares fit flattens the bell there (a, b, c some 15-20 % low on this trace)
    and leaves a structured residual; weighed by both (effective variance), it recovers
    the rig's values."""

    params = dataclasses.replace(rig.RigParams(), F_rt=3708.0, a=6.21e-4, b=3.10, c=9.03e-4)
    base = rig.SensorNoise()
    noise = dataclasses.replace(base, x_m=1.5 * base.x_m, force_N=1.5 * base.force_N)
    # A low apply voltage: the piston stops short of c, where the bell is steep.
    trace, truth = rig.simulate_rig(
        params, profile="steps", sample_rate_hz=500.0, duration_s=3.0, noise=noise, seed=27,
        v_apply_V=3.5,
    )  # fmt: skip
    assert np.max(trace["force_N"]) < 0.9 * params.F_rt
    result = fit(trace, stage="force")
    assert result.converged, result.message
    _within(result, truth["params"], ["F_rt", "a", "b", "c"], rel=0.05)
