"""Implicit derivatives of optimal solutions (``jaxmm.solver.sensitivity``, ``jaxmm.solve``).

Three levels: a QP whose optimum is, for its active set, the solution of a linear KKT system,
so that its exact derivative is the derivative of that closed form; a nonlinear stage-wise
problem against central finite differences of warm-started re-solves; the reduced iRonCub
take-off against the same, with the active set checked to be unchanged by the perturbations.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmm  # noqa: F401  (float64)
from jaxmm.solver import interior_point as ip
from jaxmm.solver import sensitivity
from jaxmm.stagewise import StagewiseFunctions, StagewiseNLP

EMPTY = jnp.zeros(0)
ACTIVE_FIELDS = ("z_lower", "z_upper", "theta_lower", "theta_upper", "path_lower", "path_upper",
                 "transition_lower", "transition_upper")


def _same_active_set(a, b):
    return all(bool(jnp.all(getattr(a, f) == getattr(b, f))) for f in ACTIVE_FIELDS)


def _no_path(args, z, theta):
    return EMPTY


def _no_transition(args, z, z_next, theta):
    return EMPTY


# --- (a) A QP: targets tracked under linear dynamics, a cap on z₀ + z₁ and a floor on z₁ -------
QP_KNOTS = 6


def _qp_cost(args, z, theta, d):
    target = d @ args["target"]  # d: the knot's row of the identity
    return 0.5 * args["weight"] * (z[0] - target[0]) ** 2 + 0.5 * (z[1] - target[1]) ** 2


def _qp_global_cost(args, theta):
    return 0.5 * (theta[0] - args["drift"]) ** 2


def _qp_dynamics(args, z, z_next, theta):
    return jnp.array([z_next[0] - z[0] - 0.5 * z[1] - 0.1 * theta[0]])


def _qp_cap(args, z, theta):
    return z[:1] + z[1:2]


QP = StagewiseFunctions(_qp_cost, _qp_global_cost, _no_path, _qp_dynamics, _qp_cap, _no_transition)
QP_PARAMETERS = dict(
    target=jnp.array([[0.1, -0.2], [0.4, -0.6], [1.4, 0.9], [1.2, 0.8], [-0.3, -0.9], [-0.5, 0.3]]),
    weight=jnp.asarray(2.0), drift=jnp.asarray(0.3), floor=jnp.asarray(-0.4), cap=jnp.asarray(0.45),
    start=jnp.asarray(0.2),
)
TIGHT = ip.Options(tolerance=1e-11, stationarity=1e-11)


def _qp(p):
    """The QP for parameters p: cost parameters in ``args``; floor, cap, start are bounds."""
    lower = jnp.full((QP_KNOTS, 2), -jnp.inf).at[:, 1].set(p["floor"]).at[0, 0].set(p["start"])
    upper = jnp.full((QP_KNOTS, 2), jnp.inf).at[0, 0].set(p["start"])
    return StagewiseNLP(
        args=dict(target=p["target"], weight=p["weight"], drift=p["drift"]), knot_data=jnp.eye(QP_KNOTS),
        z_lower=lower, z_upper=upper, theta_lower=jnp.full(1, -jnp.inf), theta_upper=jnp.full(1, jnp.inf),
        path_lower=jnp.array([-jnp.inf]), path_upper=jnp.reshape(p["cap"], (1,)), transition_lower=EMPTY,
        transition_upper=EMPTY, functions=QP,
    )


def _qp_closed_form(p, cap_rows, floor_knots):
    """x = (Z, θ) and the multipliers of the equality-constrained QP in which the given cap rows
    and floors hold with equality: the solution of its dense KKT system, linear in the bounds
    and targets."""
    nlp, n = _qp(p), 2 * QP_KNOTS + 1

    def cost(w):
        Z = w[:-1].reshape(QP_KNOTS, 2)
        knots = jax.vmap(_qp_cost, (None, 0, None, 0))(nlp.args, Z, w[-1:], nlp.knot_data)
        return jnp.sum(knots) + _qp_global_cost(nlp.args, w[-1:])

    def constraints(w):
        Z = w[:-1].reshape(QP_KNOTS, 2)
        dynamics = jax.vmap(_qp_dynamics, (None, 0, 0, None))(None, Z[:-1], Z[1:], w[-1:]).reshape(-1)
        return jnp.concatenate([dynamics, Z[0, :1] - p["start"], Z[cap_rows, 0] + Z[cap_rows, 1] - p["cap"],
                                Z[floor_knots, 1] - p["floor"]])

    w0 = jnp.zeros(n)
    H, g, A, b = jax.hessian(cost)(w0), jax.grad(cost)(w0), jax.jacfwd(constraints)(w0), -constraints(w0)
    m = A.shape[0]
    kkt = jnp.block([[H, A.T], [A, jnp.zeros((m, m))]])
    solution = jnp.linalg.solve(kkt, jnp.concatenate([-g, b]))
    return solution[:n], solution[n:]


QP_WEIGHTS = jnp.asarray(np.random.default_rng(0).normal(size=(QP_KNOTS, 2))), 0.7


def _qp_loss_of(x):
    c, c_theta = QP_WEIGHTS
    return jnp.sum(c * x[:-1].reshape(QP_KNOTS, 2)) + c_theta * x[-1]


@pytest.fixture(scope="module")
def qp():
    solve = jax.jit(ip.solve, static_argnames="options")
    solution = solve(_qp(QP_PARAMETERS), jnp.zeros((QP_KNOTS, 2)), jnp.zeros(1), options=TIGHT)
    assert ip.Status(int(solution.status)) is ip.Status.CONVERGED
    return solution


def test_qp_active_set_is_the_one_of_the_closed_form(qp):
    p = QP_PARAMETERS
    Z = np.asarray(qp.Z)
    cap_rows = np.flatnonzero(np.abs(Z.sum(axis=1) - float(p["cap"])) <= 1e-8)
    floor_knots = np.flatnonzero(np.abs(Z[:, 1] - float(p["floor"])) <= 1e-8)
    # The problem has an active and an inactive cap row, an active and an inactive floor.
    assert 0 < len(cap_rows) < QP_KNOTS and 0 < len(floor_knots) < QP_KNOTS
    x, multipliers = _qp_closed_form(p, cap_rows, floor_knots)
    assert np.abs(np.asarray(x) - np.concatenate([Z.reshape(-1), qp.theta])).max() <= 1e-8
    # Strict complementarity: the closed form's cap (upper) multipliers are positive, its floor
    # (lower) multipliers negative in f + λ·c, and every other bound is strictly inactive.
    n_eq = QP_KNOTS  # dynamics and the start
    assert np.all(np.asarray(multipliers[n_eq : n_eq + len(cap_rows)]) > 1e-3)
    assert np.all(np.asarray(multipliers[n_eq + len(cap_rows) :]) < -1e-3)
    active = sensitivity.active_set(_qp(p), qp)
    assert np.array_equal(np.flatnonzero(np.asarray(active.path_upper[:, 0])), cap_rows)
    assert np.array_equal(np.flatnonzero(np.asarray(active.z_lower[:, 1])), floor_knots)
    assert not np.any(np.asarray(active.path_lower)) and float(active.margin) > 5


def test_qp_gradient_equals_the_closed_form(qp):
    p = QP_PARAMETERS
    Z = np.asarray(qp.Z)
    cap_rows = np.flatnonzero(np.abs(Z.sum(axis=1) - float(p["cap"])) <= 1e-8)
    floor_knots = np.flatnonzero(np.abs(Z[:, 1] - float(p["floor"])) <= 1e-8)
    expected = jax.grad(lambda p: _qp_loss_of(_qp_closed_form(p, cap_rows, floor_knots)[0]))(p)

    def loss(p):
        solution = sensitivity.differentiable_solve(_qp(p), jnp.zeros((QP_KNOTS, 2)), jnp.zeros(1), TIGHT)
        return _qp_loss_of(jnp.concatenate([solution.Z.reshape(-1), solution.theta]))

    found = jax.jit(jax.grad(loss))(p)
    for name in p:  # weights, targets, drift (in args) and floor, cap, start (bounds)
        scale = np.abs(np.asarray(expected[name])).max()
        assert scale > 0 or name == "target", name
        error = np.abs(np.asarray(found[name]) - np.asarray(expected[name])).max()
        assert error <= 1e-6 * max(scale, 1e-3), (name, error, scale)


def test_qp_jvp_is_the_transpose_of_vjp_and_the_diagnostics_are_clean(qp):
    """⟨Z̄, Ż⟩ = ⟨nlp̄, ṅlp⟩ to 1e-10, with the KKT solves refined to 1e-15: at the default
    1e-13 a solve may stop after one GMRES cycle (residual 9e-14 here), and this
    KKT system's conditioning turns that into 1e-9 in the products."""
    nlp = _qp(QP_PARAMETERS)
    rng = np.random.default_rng(1)
    tangent = jax.tree.map(lambda leaf: jnp.asarray(rng.normal(size=np.shape(leaf))), nlp)
    Z_bar, theta_bar = jnp.asarray(rng.normal(size=qp.Z.shape)), jnp.asarray(rng.normal(size=qp.theta.shape))
    refined = sensitivity.Options(tolerance=1e-15)
    Z_dot, theta_dot, _, forward = jax.jit(functools.partial(sensitivity.jvp, options=refined))(nlp, qp, tangent)
    nlp_bar, backward = jax.jit(functools.partial(sensitivity.vjp, options=refined))(nlp, qp, Z_bar, theta_bar)
    left = jnp.vdot(Z_bar, Z_dot) + jnp.vdot(theta_bar, theta_dot)
    right = sum(jnp.vdot(a, b) for a, b in zip(jax.tree.leaves(nlp_bar), jax.tree.leaves(tangent)))
    assert abs(float(left - right)) <= 1e-10 * abs(float(left))
    for diagnostics in (forward, backward):
        assert bool(diagnostics.reliable()) and float(diagnostics.residual) <= 1e-12
        assert int(diagnostics.cycles) >= 1


def test_gradient_is_nan_when_the_solve_did_not_converge():
    """An unconverged solve has no KKT point to differentiate: strict mode says so with NaN."""
    stopped = ip.Options(max_iterations=2)

    def loss(p, settings):
        solution = sensitivity.differentiable_solve(_qp(p), jnp.zeros((QP_KNOTS, 2)), jnp.zeros(1), stopped,
                                                    sensitivity=settings)
        return jnp.sum(solution.Z)

    grad = jax.jit(jax.grad(loss), static_argnums=1)
    assert all(np.all(np.isnan(np.asarray(g))) for g in jax.tree.leaves(grad(QP_PARAMETERS, sensitivity.Options())))
    lenient = grad(QP_PARAMETERS, sensitivity.Options(strict=False))
    assert all(np.all(np.isfinite(np.asarray(g))) for g in jax.tree.leaves(lenient))


# --- (b) A nonlinear pendulum: reach a target angle, effort u² + 0.1 v² capped, v floored -------
SWING_KNOTS = 9


def _swing_cost(args, z, theta, d):  # z = (angle x, velocity v, torque u), θ = (duration T,)
    h = theta[0] / args["intervals"]
    return h * (0.5 * args["weight"] * (z[0] - args["target"]) ** 2 + 0.5 * z[2] ** 2)


def _swing_global_cost(args, theta):
    return 5.0 * (theta[0] - args["duration"]) ** 2


def _swing_dynamics(args, z, z_next, theta):
    h = theta[0] / args["intervals"]
    return jnp.array([z_next[0] - z[0] - 0.5 * h * (z[1] + z_next[1]),
                      z_next[1] - z[1] - h * (z_next[2] - args["gravity"] * jnp.sin(z_next[0]))])


def _swing_effort(args, z, theta):
    return z[2:3] ** 2 + 0.1 * z[1:2] ** 2


SWING = StagewiseFunctions(_swing_cost, _swing_global_cost, _no_path, _swing_dynamics, _swing_effort, _no_transition)
SWING_PARAMETERS = dict(gravity=jnp.asarray(3.0), weight=jnp.asarray(4.0), target=jnp.asarray(1.5),
                        duration=jnp.asarray(2.0), cap=jnp.asarray(3.0), floor=jnp.asarray(-0.1))


def _swing(p):
    """The pendulum for parameters p; ``args["intervals"]`` is an integer leaf."""
    lower = jnp.full((SWING_KNOTS, 3), -jnp.inf).at[:, 1].set(p["floor"]).at[0, :2].set(0.0)
    upper = jnp.full((SWING_KNOTS, 3), jnp.inf).at[0, :2].set(0.0)
    return StagewiseNLP(
        args=dict(gravity=p["gravity"], weight=p["weight"], target=p["target"], duration=p["duration"],
                  intervals=jnp.asarray(SWING_KNOTS - 1)),
        knot_data=jnp.zeros(SWING_KNOTS), z_lower=lower, z_upper=upper, theta_lower=jnp.full(1, 0.5),
        theta_upper=jnp.full(1, 5.0), path_lower=jnp.array([-jnp.inf]), path_upper=jnp.reshape(p["cap"], (1,)),
        transition_lower=EMPTY, transition_upper=EMPTY, functions=SWING,
    )


SWING_WARM = ip.Options(tolerance=1e-12, stationarity=1e-11, barrier0=1e-9, bound_push=1e-9)


def _swing_loss(p, base):
    """A smooth function of the optimum and of the multipliers, from a warm start at ``base``."""
    solution = sensitivity.differentiable_solve(_swing(p), base.Z, base.theta, SWING_WARM, base.multipliers,
                                                base.bound_multipliers)
    value = jnp.sum(jnp.sin(solution.Z)) + solution.theta[0] ** 2 + 0.1 * jnp.sum(solution.multipliers.path_inequality)
    return value, solution


def test_nonlinear_gradient_matches_central_differences_of_warm_started_solves():
    base = jax.jit(ip.solve, static_argnames="options")(_swing(SWING_PARAMETERS), jnp.zeros((SWING_KNOTS, 3)),
                                                         jnp.ones(1), options=TIGHT)
    assert ip.Status(int(base.status)) is ip.Status.CONVERGED
    active = sensitivity.active_set(_swing(SWING_PARAMETERS), base)
    assert bool(jnp.any(active.path_upper)) and not bool(jnp.all(active.path_upper))  # the cap binds somewhere
    assert float(active.margin) > 5
    value_and_grad = jax.jit(jax.value_and_grad(_swing_loss, has_aux=True))
    (_, solution), grad = value_and_grad(SWING_PARAMETERS, base)
    assert ip.Status(int(solution.status)) is ip.Status.CONVERGED
    for name, value in SWING_PARAMETERS.items():
        step = 1e-5 * max(1.0, abs(float(value)))
        values = []
        for sign in (1.0, -1.0):
            p = dict(SWING_PARAMETERS, **{name: value + sign * step})
            (loss, perturbed), _ = value_and_grad(p, base)
            assert ip.Status(int(perturbed.status)) is ip.Status.CONVERGED
            assert _same_active_set(sensitivity.active_set(_swing(p), perturbed), active), name
            values.append(float(loss))
        difference = (values[0] - values[1]) / (2 * step)
        assert abs(float(grad[name]) - difference) <= 1e-4 * abs(difference), (name, float(grad[name]), difference)


def test_integer_leaves_get_float0_and_the_rest_matches():
    base = jax.jit(ip.solve, static_argnames="options")(_swing(SWING_PARAMETERS), jnp.zeros((SWING_KNOTS, 3)),
                                                         jnp.ones(1), options=TIGHT)

    def loss(nlp):
        solution = sensitivity.differentiable_solve(nlp, base.Z, base.theta, SWING_WARM, base.multipliers,
                                                    base.bound_multipliers)
        return jnp.sum(jnp.sin(solution.Z)) + solution.theta[0] ** 2

    nlp_bar = jax.jit(jax.grad(loss, allow_int=True))(_swing(SWING_PARAMETERS))
    assert nlp_bar.args["intervals"].dtype == jax.dtypes.float0
    assert np.all(np.isfinite(np.asarray(nlp_bar.args["gravity"])))
    # The floor's cotangent lands on the lower bounds of the velocities it holds; the others
    # get O(μ) (the barrier's smoothing at μ = 1e-11).
    floored = np.asarray(sensitivity.active_set(_swing(SWING_PARAMETERS), base).z_lower[1:, 1])
    cotangent = np.abs(np.asarray(nlp_bar.z_lower[1:, 1]))
    assert floored.any() and np.all(cotangent[floored] > 1e-3)
    assert np.all(cotangent[~floored] <= 1e-8 * cotangent[floored].max())
