"""The integrator against an independent reference, and the seed's Heun trap."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ewb_ident.model.integrate import (
    MAX_SUBSTEP_S,
    NO_TERMS,
    SEED_HEUN,
    Integrator,
    MotorTerms,
    NumericalWarning,
    heun_amplification,
    integrate_motor,
)
from ewb_ident.model.params import EWBParams
from ewb_ident.model.physics import clamp_force, gap
from ewb_ident.model.predict import simulate_chain, simulate_motor

P = EWBParams()  # L/R = 2 ms


def _voltage(rate_hz: float, duration_s: float = 1.0, seed: int = 0) -> np.ndarray:
    """Piecewise-constant voltage with steps and a random part (ZOH per sample)."""
    n = int(round(duration_s * rate_hz)) + 1
    t = np.arange(n) / rate_hz
    rng = np.random.default_rng(seed)
    V = np.where(t < 0.3, 4.0, 0.0) + np.where((t > 0.6) & (t < 0.8), -3.0, 0.0)
    return V + 0.5 * rng.standard_normal(n)


def _reference(params: EWBParams, V: np.ndarray, dt: float, theta0_deg: float, tau=None):
    """Radau at tight tolerance, restarted at every sample (the ZOH discontinuities)."""
    p = {k: float(v) for k, v in params.as_dict().items()}

    def rhs(_t, s, volt):
        i, w, th = s
        load = 0.0 if tau is None else tau(s)
        return [
            (volt - p["R"] * i - p["kb"] * w) / p["L"],
            (p["kT"] * i - p["v"] * w - load) / p["M"],
            w,
        ]

    s = np.array([0.0, 0.0, np.deg2rad(theta0_deg)])
    out = [s]
    for k in range(len(V) - 1):
        sol = solve_ivp(rhs, (0.0, dt), s, method="Radau", rtol=1e-12, atol=1e-14, args=(V[k],))
        s = sol.y[:, -1]
        out.append(s)
    out = np.array(out)
    return {"current_A": out[:, 0], "theta_deg": np.rad2deg(out[:, 2])}


@pytest.mark.parametrize("rate_hz", [100.0, 1000.0])
def test_exponential_integrator_matches_fine_reference(rate_hz):
    V = _voltage(rate_hz, duration_s=0.6 if rate_hz == 100 else 0.3)
    dt = 1.0 / rate_hz
    sim = simulate_motor(P, V, dt, theta0_deg=5.0)
    ref = _reference(P, V, dt, 5.0)
    assert np.max(np.abs(np.asarray(sim["theta_deg"]) - ref["theta_deg"])) < 1e-7
    assert np.max(np.abs(np.asarray(sim["current_A"]) - ref["current_A"])) < 1e-8


def test_load_torque_converges_at_second_order():
    """A state-dependent load torque (held over each sub-step at the trapezoidal mean of
    its values): the error falls ~4x per halved sub-step, and at the rule's 0.5 ms it is
    under 1e-3 degrees (7.4e-4; ETD2RK's phi_2 correction, which this integrator had
    for a load torque given as a function, has half the error constant)."""
    rate, k_load = 200.0, 0.05

    def tau(s, params):  # a stiffening spring on the pinion angle (N*m)
        return k_load * s[2] * (1.0 + 0.1 * s[2] ** 2)

    V = _voltage(rate, duration_s=0.5)
    ref = _reference(P, V, 1 / rate, 0.0, tau=lambda s: tau(s, None))
    errors = []
    for sub in (2e-3, 1e-3, 5e-4, 2.5e-4):
        integ = Integrator(max_substep_s=sub)
        sim = simulate_motor(P, V, 1 / rate, integrator=integ, load_torque=tau)
        errors.append(np.max(np.abs(np.asarray(sim["theta_deg"]) - ref["theta_deg"])))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert errors[2] < 1e-3  # 5e-4 s: MAX_SUBSTEP_S
    assert np.all(orders[1:] > 1.8), orders  # the coarsest pair is pre-asymptotic


def test_the_substep_rule_resolves_friction():
    """Why one sub-step rule of 0.5 ms (:data:`MAX_SUBSTEP_S`): the implicit friction
    update is first order, so the angle's error halves with the step; against a fine
    reference (the same integrator at a 32nd of the rule's step) a Coulomb friction of
    the concealed stiction trace's size is resolved to under 2 % of its effect on the
    angle at 0.5 ms, not at 1 ms (the smooth load torque alone is second order:
    :func:`test_load_torque_converges_at_second_order`)."""
    dt = 2e-3
    V = jnp.asarray(_voltage(1 / dt, duration_s=1.0))
    coulomb = MotorTerms(friction=(lambda s1, force, start: (0.022, 1e-3),))
    rule = Integrator().substeps(dt, coulomb.within_sample)
    assert rule == round(dt / MAX_SUBSTEP_S) == 4

    def angle(n_sub, terms=coulomb):
        return np.asarray(integrate_motor(P, V, dt, 0.0, n_sub, terms=terms))[:, 2]

    ref = angle(32 * rule)
    effect = np.max(np.abs(ref - angle(1, NO_TERMS)))
    errors = {n: np.max(np.abs(angle(n) - ref)) / effect for n in (1, 2, 4, 8)}
    orders = np.log2([errors[n] / errors[2 * n] for n in (1, 2, 4)])
    assert np.all((orders > 0.85) & (orders < 1.2)), orders
    assert errors[rule] < 0.02 < errors[rule // 2], errors


def test_seed_heun_at_10ms_is_flagged_unstable_and_diverges():
    assert heun_amplification(P, 0.01) > 1.0
    V = _voltage(100.0, duration_s=1.0)
    with pytest.warns(NumericalWarning, match="unstable"):
        heun = simulate_motor(P, V, 0.01, integrator=SEED_HEUN)
    exact = simulate_motor(P, V, 0.01)
    assert np.max(np.abs(np.asarray(exact["current_A"]))) < 10.0
    h = np.asarray(heun["current_A"])
    assert not np.all(np.isfinite(h)) or np.max(np.abs(h)) > 1e6


def test_heun_integrates_only_the_seed_motor():
    """Heun (the seed's scheme) with a load torque is refused, not run; at a stable step,
    so that the refusal is what the test sees."""
    with pytest.raises(ValueError, match="Heun method integrates only the seed's motor"):
        simulate_motor(P, _voltage(4000.0, 0.05), 2.5e-4, integrator=SEED_HEUN,
                       load_torque=lambda s, p: 0.01 * s[2])  # fmt: skip


def test_heun_is_stable_and_second_order_at_a_small_step():
    assert heun_amplification(P, 2.5e-4) < 1.0
    V = _voltage(100.0, duration_s=0.5)
    ref = _reference(P, V, 0.01, 0.0)
    err = []
    for h in (5e-4, 2.5e-4):
        sim = simulate_motor(P, V, 0.01, integrator=Integrator(method="heun", heun_step_s=h))
        err.append(np.max(np.abs(np.asarray(sim["theta_deg"]) - ref["theta_deg"])))
    assert 3.0 < err[0] / err[1] < 5.0


def test_bell_landmarks_and_the_papers_units_slip():
    c, a = 9.57e-4, 6.295e-4
    F = clamp_force(jnp.array([c, c - a, c + a]), 3500.0, a, 2.82, c)
    np.testing.assert_allclose(np.asarray(F), [3500.0, 1750.0, 1750.0], rtol=1e-12)
    x = jnp.linspace(-8e-4, 9e-4, 50)
    flat = clamp_force(x, 3500.0, a, 2.820e-4, c)  # the paper's printed "b = 2.820e-4 m"
    assert np.max(np.abs(np.asarray(flat) - 1750.0)) < 5.0
    assert float(gap(0.0, 3.8e-9, 1.5e-6, -8.4e-4)) == pytest.approx(-8.4e-4)


def test_chain_gradient_is_finite_at_the_bell_centre():
    import jax

    V = _voltage(200.0, 0.5)

    def loss(c):
        out = simulate_chain(P.replace(c=c), V, 0.005)
        return jnp.sum(out["force_N"])

    g = jax.grad(loss)(jnp.asarray(9.57e-4))
    assert np.isfinite(float(g))
    # Exactly at the centre (x == c), where |x - c|^(2b) has a log singularity: every
    # derivative of the force stays finite (the floor in physics.clamp_force).
    c, a = 9.57e-4, 6.295e-4
    grads = jax.grad(lambda x, a, b, c: clamp_force(x, 3500.0, a, b, c), argnums=(0, 1, 2, 3))(
        jnp.asarray(c), jnp.asarray(a), jnp.asarray(2.82), jnp.asarray(c)
    )
    assert all(np.isfinite(float(d)) for d in grads)


def test_noise_of_a_quantised_channel_is_at_least_its_rounding_error():
    from ewb_ident.data.metrics import noise_sigma, quantisation_step

    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 3.0, 3000)
    y = 100.0 * np.sin(t) + rng.normal(0.0, 0.05, t.size)
    q = 0.87890625  # 12 bits over 3600 deg
    yq = q * np.round(y / q)
    assert quantisation_step(yq) == pytest.approx(q)
    assert quantisation_step(y) == 0.0
    true_sd = float(np.std(yq - 100.0 * np.sin(t)))
    assert noise_sigma(yq) == pytest.approx(true_sd, rel=0.1)
    # a step below the white noise changes nothing
    F = np.round(3000.0 * np.sin(t) ** 2 + rng.normal(0.0, 7.0, t.size))
    assert noise_sigma(F) == pytest.approx(7.0, rel=0.1)


@pytest.mark.parametrize("ratio", [0.3, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0])
def test_noise_about_one_step_of_a_grid_is_estimated_to_a_few_per_cent(ratio):
    """The MAD of values on a grid is on the grid: with white noise of 0.5 to 2 steps
    the plain robust scale of the second differences is off by up to 20 %, and a clean
    12-bit channel's residual then passes for missing physics."""
    from ewb_ident.data.metrics import noise_sigma

    rng = np.random.default_rng(int(10 * ratio))
    q = 3e-3 / 4096  # 12 bits over 3 mm, m
    t = np.linspace(0.0, 3.0, 3000)
    x = 4e-4 * np.sin(2.0 * np.pi * 0.7 * t) + 2e-4 * t
    noisy = x + rng.normal(0.0, ratio * q, t.size)
    xq = q * np.round(noisy / q)
    true_sd = float(np.std(xq - x))
    assert noise_sigma(xq) == pytest.approx(true_sd, rel=0.06)
    # a residual near the grid (measured minus a smooth model) when told the step
    assert noise_sigma(xq - x, step=q) == pytest.approx(true_sd, rel=0.06)
