"""Fitting foundation parameters to trajectories (rbo_jax.fitting)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rbo_jax.fitting import TrajectoryData, fit, residuals
from rbo_jax.fitting._residuals import Spec as _Spec
from rbo_jax.fitting._residuals import loss as _loss
from rbo_jax.fitting._residuals import loss_and_grad as _loss_and_grad
from rbo_jax.foundations import BarrierFoundation, IsotropicFoundation, QuadraticFoundation
from rbo_jax.inertia import transversely_isotropic_inertia
from rbo_jax.kinematics import turn_tensor
from rbo_jax.loads import Friction
from rbo_jax.model import RigidBodyOscillator
from rbo_jax.simulate import simulate

K = jnp.array([0.0, 0.0, 1.0])
A = transversely_isotropic_inertia(1.0, 0.6, K)
INITS = [
    (jnp.array([0.8, -0.3, 0.5]), jnp.array([0.2, 1.1, -0.7])),
    (jnp.array([0.2, 0.6, -0.3]), jnp.array([-0.5, 0.3, 0.9])),
]


def _synthetic(model, inits, ts, **kwargs):
    out = []
    for th0, Om0 in inits:
        tr = simulate(model, th0, Om0, ts, rtol=1e-12, atol=1e-12)
        out.append(
            TrajectoryData(ts, theta=tr.theta, Omega=tr.Omega, theta0=th0, Omega0=Om0, **kwargs)
        )
    return out


@pytest.mark.slow  # cost: ~20 s of compilation
def test_noise_free_barrier_parameters_recovered_from_30_percent_off():
    """c, d, alpha, beta of (4.49) recovered to ≤ 1e-6 relative from noise-free data, starting
    30 % off (Levenberg-Marquardt through the ODE solver)."""
    truth = dict(c=1.0, d=2.0, alpha=1.5, beta=1.2)
    true_model = RigidBodyOscillator(A, BarrierFoundation(k=K, **truth))
    datas = _synthetic(true_model, INITS, jnp.linspace(0.0, 8.0, 100))
    start = RigidBodyOscillator(A, BarrierFoundation(1.3, 1.4, 1.95, 0.84, K))
    res = fit(
        start,
        datas,
        lambda m: (m.foundation.c, m.foundation.d, m.foundation.alpha, m.foundation.beta),
    )
    assert res.converged, res.message
    fitted = np.array([float(v) for v in res.params])
    np.testing.assert_allclose(fitted, list(truth.values()), rtol=1e-6)
    assert res.loss_history[0] > 1e6 * res.loss_history[-1]
    assert float(res.model.foundation.alpha) == pytest.approx(truth["alpha"], rel=1e-6)


def _rotation_noise(key, Q, sigma):
    """Q_obs = Q(η)·Q with η ~ N(0, σ² E) per sample: attitude noise of σ rad."""
    eta = sigma * jax.random.normal(key, (Q.shape[0], 3))
    return jax.vmap(lambda e, q: turn_tensor(e) @ q)(eta, Q)


def _noisy_fits(draws, sigma=1e-3):
    """Fits of c and d to ``draws`` noise draws of σ rad on the attitudes of one trajectory."""
    truth = np.array([1.0, 2.0])
    true_model = RigidBodyOscillator(A, QuadraticFoundation(truth[0], truth[1], K))
    th0, Om0 = INITS[0]
    ts = jnp.linspace(0.0, 6.0, 60)
    Q_true = simulate(true_model, th0, Om0, ts, rtol=1e-12, atol=1e-12).turn_tensor
    start = RigidBodyOscillator(A, QuadraticFoundation(1.2, 1.7, K))
    estimates, stderrs = [], []
    for i in range(draws):
        Q_obs = _rotation_noise(jax.random.PRNGKey(i), Q_true, sigma)
        data = TrajectoryData(ts, Q=Q_obs, theta0=th0, Omega0=Om0, sigma_theta=sigma)
        res = fit(start, data, lambda m: (m.foundation.c, m.foundation.d))
        assert res.converged, res.message
        estimates.append([float(v) for v in res.params])
        stderrs.append([float(v) for v in res.stderr])
    return truth, np.array(estimates), np.array(stderrs)


def test_noisy_fit_lies_within_its_standard_errors():
    """σ = 1e-3 rad attitude noise, two draws: each estimate lies within 3 Gauss-Newton
    standard errors of the truth, and the standard errors are those of a well-determined fit
    (1e-5 to 1e-2 of the values; the spread over 20 draws: the complete tier)."""
    truth, estimates, stderrs = _noisy_fits(2)
    assert np.all(np.abs(estimates - truth) <= 3 * stderrs)
    assert np.all((stderrs > 1e-5 * truth) & (stderrs < 1e-2 * truth)), stderrs


@pytest.mark.slow  # cost: ~15-20 s, 20 fits of noisy data
def test_noisy_fit_standard_errors_match_the_spread():
    """σ = 1e-3 rad attitude noise: every estimate lies within 3 Gauss-Newton standard errors of
    the truth, and the standard errors agree with the spread over 20 noise draws within 1.5x."""
    truth, estimates, stderrs = _noisy_fits(20)
    assert np.all(np.abs(estimates - truth) <= 3 * stderrs)
    ratio = estimates.std(axis=0, ddof=1) / stderrs.mean(axis=0)
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), ratio


@pytest.mark.slow  # cost: ~20 s, reverse mode through diffrax compiled
def test_loss_gradient_matches_finite_differences():
    """Reverse-mode gradient of the loss through diffrax = central finite differences."""
    true_model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    ts = jnp.linspace(0.0, 3.0, 30)
    data = tuple(_synthetic(true_model, INITS[:1], ts))
    model = RigidBodyOscillator(A, QuadraticFoundation(1.1, 1.8, K))
    spec = _Spec(
        paths=tuple(
            p
            for p, leaf in jax.tree_util.tree_flatten_with_path(model)[0]
            if leaf is model.foundation.c or leaf is model.foundation.d
        ),
        transforms=("log", "log"),
        fit_initial_state=False,
        rtol=1e-12,
        atol=1e-12,
        forward=False,
    )
    u = {"p": (jnp.log(1.1), jnp.log(1.8))}
    _, g = _loss_and_grad(u, model, data, spec)
    h = 1e-6
    for i in range(2):
        up = {"p": tuple(x + (h if j == i else 0.0) for j, x in enumerate(u["p"]))}
        um = {"p": tuple(x - (h if j == i else 0.0) for j, x in enumerate(u["p"]))}
        fd = (float(_loss(up, model, data, spec)) - float(_loss(um, model, data, spec))) / (2 * h)
        assert float(g["p"][i]) == pytest.approx(fd, rel=1e-6)


class _HalfC(eqx.Module):
    """F(θ²) = ½cθ² with c a differentiable leaf."""

    c: jax.Array

    def __init__(self, c):
        self.c = jnp.asarray(c, dtype=float)

    def __call__(self, s):
        return 0.5 * self.c * s


def test_attitude_data_wrapping_through_pi(capsys):
    """A large plane oscillation (|θ| up to ~3.9 rad): the observed principal turn-vectors jump at
    |θ| = π, but the rotation distance turn_vector(Q_obsᵀ·Q) fits c exactly (``progress=True``:
    the iterations and their loss on a bar)."""
    from rbo_jax.kinematics import turn_vector

    c_true = 1.5
    model = RigidBodyOscillator(jnp.eye(3), IsotropicFoundation(_HalfC(c_true)))
    n = jnp.array([1.0, 2.0, -0.5]) / jnp.linalg.norm(jnp.array([1.0, 2.0, -0.5]))
    th0, Om0 = 2.8 * n, 3.0 * n
    ts = jnp.linspace(0.0, 4.0, 80)
    tr = simulate(model, th0, Om0, ts, rtol=1e-12, atol=1e-12)
    principal = jax.vmap(turn_vector)(tr.turn_tensor)
    assert float(jnp.max(jnp.linalg.norm(tr.theta, axis=1))) > jnp.pi + 0.5
    assert float(jnp.max(jnp.abs(principal - tr.theta))) > 1.0  # the data does wrap
    data = TrajectoryData(ts, theta=principal, theta0=th0, Omega0=Om0)
    start = RigidBodyOscillator(jnp.eye(3), IsotropicFoundation(_HalfC(0.7 * c_true)))
    res = fit(start, data, lambda m: m.foundation.F.c, progress=True)
    assert res.converged, res.message
    assert float(res.params[0]) == pytest.approx(c_true, rel=1e-6)
    err = capsys.readouterr().err
    assert "fit:" in err and "loss=" in err


def test_partial_observations_omega_only_and_masked_theta():
    """Only some quantities/components observed: ω alone, or θ with its z component masked."""
    true_model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    th0, Om0 = INITS[0]
    ts = jnp.linspace(0.0, 6.0, 60)
    tr = simulate(true_model, th0, Om0, ts, rtol=1e-12, atol=1e-12)
    start = RigidBodyOscillator(A, QuadraticFoundation(1.25, 1.6, K))
    sel = lambda m: (m.foundation.c, m.foundation.d)  # noqa: E731
    res = fit(start, TrajectoryData(ts, omega=tr.omega, theta0=th0, Omega0=Om0), sel)
    np.testing.assert_allclose([float(v) for v in res.params], [1.0, 2.0], rtol=1e-6)
    w = np.ones((60, 3))
    w[:, 2] = 0.0
    theta_obs = np.array(tr.theta)
    theta_obs[:, 2] = np.nan  # unobserved: NaN is fine under weight 0
    res = fit(
        start, TrajectoryData(ts, theta=theta_obs, theta_weight=w, theta0=th0, Omega0=Om0), sel
    )
    np.testing.assert_allclose([float(v) for v in res.params], [1.0, 2.0], rtol=1e-6)


# ---------------------------------------------------------------------------------------------
# External check against MuJoCo
# ---------------------------------------------------------------------------------------------


def _quat_to_mat(q):
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _mujoco_ball_joint(c, b, inertia, theta0, Omega0, t1, n, dt=1e-4):
    """A body on a MuJoCo ball joint with `stiffness` c and `damping` b, no gravity. MuJoCo's
    ball joint: qpos is the unit quaternion (w, x, y, z) of the body, qvel the angular velocity
    in the body (local) frame, i.e. Ω; the passive spring torque is −c times the rotation vector
    (|θ| < π) and the damping torque −b·qvel, i.e. −bω in the world frame."""
    import mujoco

    xml = f"""<mujoco><option timestep="{dt}" integrator="RK4" gravity="0 0 0"/>
    <worldbody><body name="b"><joint name="j" type="ball" stiffness="{c}" damping="{b}"/>
    <inertial pos="0 0 0" mass="1" diaginertia="{inertia[0]} {inertia[1]} {inertia[2]}"/>
    </body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    angle = np.linalg.norm(theta0)
    d.qpos[:] = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * theta0 / angle])
    d.qvel[:] = Omega0
    steps = int(round(t1 / (n - 1) / dt))
    ts, Qs, Oms = [], [], []
    for i in range(n):
        ts.append(d.time)
        Qs.append(_quat_to_mat(d.qpos.copy()))
        Oms.append(d.qvel.copy())
        if i < n - 1:
            mujoco.mj_step(m, d, nstep=steps)
    return np.array(ts), np.array(Qs), np.array(Oms)


@pytest.mark.slow  # cost: ~15 s, MuJoCo data and a fit
def test_mujoco_ball_joint_stiffness_and_damping_recovered():
    """External check: trajectories of MuJoCo (RK4, dt = 1e-4) for a body on a ball joint with
    stiffness c and damping b are fitted with the isotropic foundation U = ½cθ² and Friction(b);
    c and b are recovered to ≤ 1e-4 relative."""
    c, b, inertia = 2.0, 0.1, (1.0, 1.3, 0.7)
    A_diag = jnp.diag(jnp.asarray(inertia))
    datas = []
    for th0, Om0 in [
        (np.array([0.5, -0.3, 0.8]), np.array([0.4, 1.2, -0.6])),
        (np.array([-0.2, 0.7, 0.1]), np.array([1.0, -0.3, 0.5])),
    ]:
        ts, Qs, Oms = _mujoco_ball_joint(c, b, inertia, th0, Om0, 5.0, 101)
        datas.append(TrajectoryData(ts, Q=Qs, Omega=Oms, theta0=th0, Omega0=Om0))
    start = RigidBodyOscillator(A_diag, QuadraticFoundation(1.4 * c, 1.4 * c, K), Friction(0.7 * b))
    # U = ½cθ² is QuadraticFoundation(c, c, k); fit c = d (one parameter) and b.
    res = fit(start, datas, lambda m: (m.foundation.c, m.foundation.d, m.loads[0].b))
    assert res.converged, res.message
    c_fit, d_fit, b_fit = (float(v) for v in res.params)
    assert c_fit == pytest.approx(c, rel=1e-4)
    assert d_fit == pytest.approx(c, rel=1e-4)
    assert b_fit == pytest.approx(b, rel=1e-4)


# ---------------------------------------------------------------------------------------------
# Optimisers, staging, errors
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "optimizer",
    [
        pytest.param("adam", marks=pytest.mark.slow),
        pytest.param("lbfgs", marks=pytest.mark.slow),
        "gauss_newton",
    ],
)
def test_other_optimizers_decrease_the_loss(optimizer):
    true_model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    data = _synthetic(true_model, INITS[:1], jnp.linspace(0.0, 3.0, 30))
    start = RigidBodyOscillator(A, QuadraticFoundation(1.2, 1.7, K))
    res = fit(
        start,
        data,
        lambda m: (m.foundation.c, m.foundation.d),
        optimizer=optimizer,
        max_steps=15,
        learning_rate=0.05,
    )
    assert res.loss_history[-1] < 0.2 * res.loss_history[0]


@pytest.mark.slow  # cost: ~20 s, staged fits compiled
def test_staged_horizons_and_initial_state_fit():
    """horizons=(0.5, 1) fits half the record first; fit_initial_state recovers a wrong θ0, Ω0."""
    true_model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    th0, Om0 = INITS[0]
    ts = jnp.linspace(0.0, 6.0, 60)
    tr = simulate(true_model, th0, Om0, ts, rtol=1e-12, atol=1e-12)
    data = TrajectoryData(ts, theta=tr.theta, Omega=tr.Omega, theta0=th0 + 0.05, Omega0=Om0 - 0.05)
    start = RigidBodyOscillator(A, QuadraticFoundation(1.2, 1.7, K))
    res = fit(
        start,
        data,
        lambda m: (m.foundation.c, m.foundation.d),
        fit_initial_state=True,
        horizons=(0.5, 1.0),
    )
    np.testing.assert_allclose([float(v) for v in res.params], [1.0, 2.0], rtol=1e-6)
    np.testing.assert_allclose(res.initial_states[0][0], th0, atol=1e-7)
    np.testing.assert_allclose(res.initial_states[0][1], Om0, atol=1e-7)


def test_bad_data_is_refused_before_compilation():
    ts = np.linspace(0, 1, 5)
    th = np.zeros((5, 3))
    with pytest.raises(ValueError, match="strictly increasing"):
        TrajectoryData(ts[::-1], theta=th)
    with pytest.raises(ValueError, match="empty"):
        TrajectoryData(np.array([]), theta=np.zeros((0, 3)))
    with pytest.raises(ValueError, match="samples but ts"):
        TrajectoryData(ts, theta=np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"shape \(n, 3\)"):
        TrajectoryData(ts, omega=np.zeros((5, 2)), theta0=np.zeros(3), Omega0=np.zeros(3))
    bad = th.copy()
    bad[2, 1] = np.inf
    with pytest.raises(ValueError, match="theta contains inf"):
        TrajectoryData(ts, theta=bad, Omega0=np.zeros(3))
    with pytest.raises(ValueError, match="nothing observed"):
        TrajectoryData(ts)
    with pytest.raises(ValueError, match="Omega0 is needed"):
        TrajectoryData(ts, theta=th)
    with pytest.raises(ValueError, match="sigma_theta"):
        TrajectoryData(ts, theta=th, Omega0=np.zeros(3), sigma_theta=-1.0)
    model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    data = TrajectoryData(ts, theta=th, Omega0=np.zeros(3))
    with pytest.raises(ValueError, match="empty"):
        fit(model, [], lambda m: m.foundation.c)
    with pytest.raises(ValueError, match="optimizer"):
        fit(model, data, lambda m: m.foundation.c, optimizer="newton")
    with pytest.raises(ValueError, match="horizons"):
        fit(model, data, lambda m: m.foundation.c, horizons=(1.0, 0.5))
    with pytest.raises(ValueError, match="params"):
        fit(model, data, lambda m: m.foundation.nope)
    with pytest.raises(ValueError, match="leaves of the model"):
        fit(model, data, lambda m: jnp.asarray(1.0))
    with pytest.raises(ValueError, match="solve_max_steps"):
        fit(model, data, lambda m: m.foundation.c, solve_max_steps=0)


@pytest.mark.slow  # cost: ~15 s of compilation
def test_solver_step_budget_reaches_the_ode_solves():
    """solve_max_steps is the step budget of every ODE solve inside the fit: 3 steps cannot cover
    t in [0, 3], so the residuals are not finite at the start and the fit says so; the default
    budget fits the same data."""
    true_model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    (data,) = _synthetic(true_model, INITS[:1], jnp.linspace(0.0, 3.0, 30))
    start = RigidBodyOscillator(A, QuadraticFoundation(1.3, 2.0, K))
    with pytest.raises(FloatingPointError, match="not finite at the starting point"):
        fit(start, data, lambda m: m.foundation.c, solve_max_steps=3)
    res = fit(start, data, lambda m: m.foundation.c)
    assert res.converged and abs(float(res.params[0]) - 1.0) < 1e-6


def test_residuals_are_zero_on_the_generating_model():
    true_model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    (data,) = _synthetic(true_model, INITS[:1], jnp.linspace(0.0, 3.0, 30))
    r = residuals(true_model, data, rtol=1e-12, atol=1e-12)
    assert r.shape == (30 * 3 * 2,)
    assert float(jnp.max(jnp.abs(r))) < 1e-9


@pytest.mark.parametrize("t0", [None, 0.0], ids=["t0=ts[0]", "t0<ts[0]"])
def test_fast_simulate_residuals_vanish_on_the_generating_model(t0):
    """The fit's residuals through fast_simulate (which starts at its first time) from the state
    at t0: both when t0 is the first sample and when it is before it."""
    true_model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    th0, Om0 = INITS[0]
    ts = jnp.linspace(0.0 if t0 is None else 0.5, 3.0, 30)
    tr = simulate(
        true_model,
        th0,
        Om0,
        jnp.concatenate([jnp.zeros(1), ts]) if t0 is not None else ts,
        rtol=1e-12,
        atol=1e-12,
    )
    k = 0 if t0 is None else 1
    data = TrajectoryData(ts, theta=tr.theta[k:], Omega=tr.Omega[k:], theta0=th0, Omega0=Om0, t0=t0)
    r = residuals(true_model, data, rtol=1e-12, atol=1e-12, integrator="fast_simulate")
    assert r.shape == (30 * 3 * 2,)
    assert float(jnp.max(jnp.abs(r))) < 1e-9
    wrong = RigidBodyOscillator(A, QuadraticFoundation(1.1, 2.0, K))
    assert float(jnp.max(jnp.abs(residuals(wrong, data, integrator="fast_simulate")))) > 1e-3


@pytest.mark.slow  # cost: ~20 s, two fits compiled
def test_fast_simulate_and_simulate_fits_agree():
    """The default fit (Levenberg-Marquardt on fast_simulate's forward mode) and the fit through
    simulate (diffrax, ForwardMode) recover the same parameters, the truth, from 30 % off."""
    true_model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K), [Friction(0.1)])
    (data,) = _synthetic(true_model, INITS[:1], jnp.linspace(0.0, 4.0, 41))
    start = RigidBodyOscillator(A, QuadraticFoundation(1.3, 1.4, K), [Friction(0.13)])

    def select(m):
        return m.foundation.c, m.foundation.d, m.loads[0].b

    fast = fit(start, data, select)
    slow = fit(start, data, select, integrator="simulate")
    for res in (fast, slow):
        assert res.converged, res.message
        np.testing.assert_allclose([float(v) for v in res.params], [1.0, 2.0, 0.1], rtol=1e-6)
    np.testing.assert_allclose(
        [float(v) for v in fast.params], [float(v) for v in slow.params], rtol=1e-7
    )


def test_fit_programs_hold_no_host_callback():
    """JAX's persistent compilation cache keeps no program with a host callback: the compiled
    residuals and Jacobian of a fit through fast_simulate hold none (the solves' checks are in
    their status), so a second process loads the program instead of compiling it."""
    from rbo_jax.fitting._residuals import leaf_paths, residuals_and_jacobian

    model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    (data,) = _synthetic(model, INITS[:1], jnp.linspace(0.0, 1.0, 5))
    values = (model.foundation.c, model.foundation.d)
    u = {"p": tuple(jnp.log(v) for v in values)}

    def program(integrator):
        spec = _Spec(
            paths=leaf_paths(model, values),
            transforms=("log", "log"),
            fit_initial_state=False,
            rtol=1e-10,
            atol=1e-10,
            forward=True,
            integrator=integrator,
        )
        return residuals_and_jacobian.lower(u, model, (data,), spec).as_text()

    assert "callback" not in program("fast_simulate")


@pytest.mark.slow  # integration: fits in fresh processes, ~30 s
def test_fit_program_is_kept_by_the_program_store(tmp_path, monkeypatch):
    """With the command line's program store on, the fit's program is exported once and a
    second process (here: the in-memory programs and JAX's caches cleared) loads it instead of
    tracing it; the fit is the same to the last bit and recovers the truth."""
    from rbo_jax import _programs
    from rbo_jax.fitting import _residuals

    traces = []
    vector = _residuals.residual_vector
    monkeypatch.setattr(
        _residuals, "residual_vector", lambda *a: traces.append(1) or vector(*a)
    )  # called when traced
    model = RigidBodyOscillator(A, QuadraticFoundation(1.3, 1.5, K))
    truth = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    (data,) = _synthetic(truth, INITS[:1], jnp.linspace(0.0, 1.0, 6))
    kwargs = dict(integrator="fast_simulate", max_steps=20)
    try:
        _programs.enable_program_store(tmp_path)
        first = fit(model, data, lambda m: (m.foundation.c, m.foundation.d), **kwargs)
        assert len(list(tmp_path.glob("*.jaxexport"))) == 1
        _programs.enable_program_store(tmp_path)
        jax.clear_caches()
        traces.clear()
        again = fit(model, data, lambda m: (m.foundation.c, m.foundation.d), **kwargs)
        assert traces == [], "the stored fit program was traced again"
    finally:
        _programs.enable_program_store(None)
    np.testing.assert_array_equal(np.asarray(again.params), np.asarray(first.params))
    np.testing.assert_allclose(np.asarray(first.params), [1.0, 2.0], rtol=1e-6)


def test_integrator_option_is_checked():
    model = RigidBodyOscillator(A, QuadraticFoundation(1.0, 2.0, K))
    data = TrajectoryData(np.linspace(0, 1, 5), theta=np.zeros((5, 3)), Omega0=np.zeros(3))
    with pytest.raises(ValueError, match="integrator must be one of"):
        fit(model, data, lambda m: m.foundation.c, integrator="rk4")
    with pytest.raises(ValueError, match="reverse-mode"):
        fit(model, data, lambda m: m.foundation.c, optimizer="adam", integrator="fast_simulate")
    with pytest.raises(ValueError, match="forward mode only"):
        residuals(model, data, integrator="fast_simulate", adjoint=object())
