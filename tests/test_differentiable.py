"""Gradients of iRonCub's optimal take-off with respect to its task (``jaxmm.solve``)
and weight tuning with optax (``jaxmm.tuning``), on the reduced take-off of ``conftest``.

The gradient is the implicit derivative at the solution; the reference is central differences
of re-solves warm-started from that solution, which keep its contact schedule (checked). Every
compiled program here is shared with ``test_solve_task`` (same task structure and options):
the cold and warm-started solves, and one adjoint program. ``jax.grad`` through a
differentiable solve compiles a program of its own and is marked slow (``pytest -m slow``).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jaxmm import analysis, solve, tasks, tuning
from jaxmm.solve import solve_task
from jaxmm.solver import interior_point as ip

from conftest import REDUCED_TAKE_OFF

AGREE = 1e-4  # relative: the goal; see test_the_take_off_gradient_matches_central_differences_of_re_solves


def impulse(task, trajectory):
    """Total thrust impulse Σ_k T[k] Δt [N s] (the rectangle rule over knots 0..N−1)."""
    return jnp.sum(trajectory.knots.thrust[:-1]) * trajectory.total_time / task.n_intervals


def _final_height(task, value):
    return dataclasses.replace(task, params=dataclasses.replace(
        task.params, final_com=task.params.final_com.at[2].set(value)))


def _weight(name):
    def set_weight(task, value):
        return dataclasses.replace(task, weights=dataclasses.replace(task.weights, **{name: value}))
    return set_weight


CASES = {  # name: (task with the parameter set to a value, its cotangent in task_bar, its value, relative step)
    "final CoM height": (_final_height, lambda bar: bar.params.final_com[2], lambda task: task.params.final_com[2], 1e-3),
    "weight com_vel": (_weight("com_vel"), lambda bar: bar.weights.com_vel, lambda task: task.weights.com_vel, 1e-2),
    "weight final_thrust": (_weight("final_thrust"), lambda bar: bar.weights.final_thrust,
                            lambda task: task.weights.final_thrust, 1e-2),
}


@pytest.fixture(scope="module")
def polished(solved_take_off):
    """The take-off re-solved from its solution in the same scaling (3 iterations): the point
    the gradient is taken at and the finite-difference re-solves start from."""
    task, result = solved_take_off
    again = solve_task(task, warm_start=result, same_scaling=True)
    assert again.status is ip.Status.CONVERGED, again.status.message
    return task, again


@pytest.mark.parametrize("name", list(CASES))
def test_the_take_off_gradient_matches_central_differences_of_re_solves(polished, name):
    """d(thrust impulse)/d(parameter) at the take-off's solution, against (J(p + h) − J(p − h)) / 2h
    from re-solves warm-started at that solution in the same scaling (``same_scaling``).

    Both matter (measured). Without ``same_scaling`` a re-solve recomputes the cost
    factor at its start, and that factor is ∝ 1 / w_final_thrust (the largest cost gradient is the
    final-thrust term): the barrier problem at μ > 0 then changes with the weight through its
    scaling too, and the differences of final_thrust disagree with the implicit derivative (which
    holds the scaling) by 2.2e-3, while the final CoM height, which leaves the factor alone,
    agrees to 5e-8. And the step must make J(p ± h) differ by more than the re-solves' own
    accuracy (they stop after 2–4 iterations once within tolerance): h = 1e-4 p gave 5e-4 on
    the height and com_vel; the steps used give 4.5e-7 (height, 1e-3), 3.8e-5 (com_vel, 1e-2;
    its derivative is tiny: −1.8e-7 N s per unit of a 1e7 weight) and ≈ 4e-6 (final_thrust, 1e-2).
    For final_thrust, 1e-3 is too small where the take-off's rounding (one core per process, as
    the test workers run) leaves a polished point from which the ±h re-solves stop after two
    iterations on a slope of −0.042 against the optimum's 0.0116, for every h from 1e-4 to 1e-3;
    at 1e-2 they take 5–6 iterations and agree to ≈ 4e-6 there and to 1e-5 with more threads.
    Tightening the solver's stationarity instead made it worse (20-iteration re-solves, adjoint
    residual 3e-8)."""
    task, result = polished
    value, task_bar, diagnostics = solve.gradient(task, result, impulse)
    assert bool(diagnostics.reliable()) and float(diagnostics.residual) <= 1e-10, diagnostics
    assert float(value) == pytest.approx(float(impulse(task, result.trajectory)), rel=1e-14)
    with_value, cotangent, parameter, step = CASES[name]
    x = float(parameter(task))
    h = step * abs(x)
    schedule = analysis.airborne_corners(result.trajectory)
    values = []
    for sign in (1.0, -1.0):
        perturbed = with_value(task, jnp.asarray(x + sign * h, dtype=float))  # strong float64: no recompilation
        again = solve_task(perturbed, warm_start=result, same_scaling=True)
        assert again.status is ip.Status.CONVERGED, again.status.message
        np.testing.assert_array_equal(analysis.airborne_corners(again.trajectory), schedule)
        values.append(float(impulse(perturbed, again.trajectory)))
    difference = (values[0] - values[1]) / (2 * h)
    derivative = float(cotangent(task_bar))
    print(f"{name}: implicit {derivative:.10g}, central difference {difference:.10g}, "
          f"relative error {abs(derivative - difference) / abs(difference):.2g}")
    assert abs(difference) > 0
    assert abs(derivative - difference) <= AGREE * abs(difference)


def test_tuning_moves_the_thrust_impulse_towards_a_target(solved_take_off):
    """Three Adam steps on log(com_vel, final_thrust) towards an impulse 1 % below the solution's:
    the loss falls, every solve converges, the history is complete, and the weights returned are
    those of the lowest loss seen."""
    task, result = solved_take_off
    target = 0.99 * float(impulse(task, result.trajectory))

    def loss(task, trajectory):
        return (impulse(task, trajectory) / target - 1.0) ** 2

    seen = []
    tuned = tuning.tune_weights(task, loss, names=("com_vel", "final_thrust"), optimizer=optax.adam(0.2), steps=3,
                                warm_start=result, callback=lambda step, value, weights: seen.append(value))
    print(tuned)
    assert tuned.stopped == "3 steps"
    assert len(tuned.loss) == 3 and seen == list(tuned.loss)
    assert np.all(tuned.status == int(ip.Status.CONVERGED))
    assert tuned.loss[-1] < tuned.loss[0]
    best = int(np.argmin(tuned.loss))
    for i, name in enumerate(tuned.names):
        assert float(getattr(tuned.weights, name)) == pytest.approx(float(np.exp(tuned.log_weights[best, i])), rel=1e-12)
    assert np.all(np.isfinite(tuned.gradients)) and np.all(tuned.gradients != 0)


def test_tuning_rejects_unknown_and_zero_weights():
    task = tasks.scenario("take_off", **REDUCED_TAKE_OFF)
    with pytest.raises(ValueError, match="unknown weight name"):
        tuning.tune_weights(task, impulse, names=("com_velocity",))
    with pytest.raises(ValueError, match="not positive"):
        tuning.tune_weights(task, impulse, names=("thrust",))  # 0 in the take-off


@pytest.mark.slow
def test_jax_grad_through_a_differentiable_solve_is_the_adjoint_gradient(polished):
    """``jax.grad`` of a loss through ``solve_task(..., differentiable=True)`` (the solve's custom
    VJP) equals ``solve.gradient`` (one adjoint solve, no re-solve) at the optimum that solve
    found: the two implicit derivatives, through the solve and after it, at the same point."""
    task, result = polished

    def loss(weights):
        tuned = dataclasses.replace(task, weights=weights)
        again = solve_task(tuned, warm_start=result, differentiable=True)
        return impulse(tuned, again.trajectory), again

    through, again = jax.grad(loss, has_aux=True)(task.weights)
    assert again.status is ip.Status.CONVERGED, again.status.message
    _, task_bar, diagnostics = solve.gradient(task, again, impulse)
    assert bool(diagnostics.reliable()), diagnostics
    for name in ("com_vel", "final_thrust", "thrust"):
        a, b = float(getattr(through, name)), float(getattr(task_bar.weights, name))
        assert b != 0.0 and abs(a - b) <= 1e-8 * abs(b), (name, a, b)


def test_a_differentiable_solve_takes_no_budget_or_interrupts():
    task = tasks.scenario("take_off", **REDUCED_TAKE_OFF)
    with pytest.raises(ValueError, match="a differentiable solve is one call: it takes no time_budget"):
        solve_task(task, differentiable=True, time_budget=10.0)
    with pytest.raises(TypeError, match="differentiable must be a bool or sensitivity.Options, got str"):
        solve_task(task, differentiable="yes")
