"""Solve a task and differentiate the optimum with respect to the task's numbers.

``solve_task_differentiable`` is ``optimise.solve_task`` with reverse-mode derivatives: the
optimal trajectory, multipliers and objective are differentiable with respect to every float
leaf of the ``Task`` (cost weights, targets x₀ and x_N, the mid-horizon height, jet
coefficients, bounds, the robot model's numbers), by implicit differentiation of the KKT
conditions at the solution (``jaxmm.solver.sensitivity``), never through the solver's
iterations:

    def impulse(weights):
        task = dataclasses.replace(base, weights=weights)
        result = solve_task_differentiable(task, warm_start=previous)
        knots = result.trajectory.knots
        return jnp.sum(knots.thrust[:-1]) * result.trajectory.total_time / task.n_intervals

    jax.grad(impulse)(base.weights)

``gradient`` differentiates a solution already found (by ``optimise.solve_task``, say) without
solving again: one adjoint solve at that solution, compiled apart from the solver.

The derivative is that of the local optimum the solver found, with its active set held fixed
(smoothed by the final barrier parameter, see ``jaxmm.solver.sensitivity``): it is the true
derivative where the active set does not change under the perturbation. Gradients are NaN when
the solve did not converge or the KKT system could not be solved accurately (see
``sensitivity.Options``).
"""

import dataclasses

import jax

from jaxmm import compilation
from jaxmm.optimise import DEFAULT_OPTIONS, prepare, task_solution
from jaxmm.solver import sensitivity
from jaxmm.transcription import nlp as transcription


@compilation.jit(static_argnames=("options", "settings"))
def _solve(task, guess, options, settings, multipliers, bound_multipliers):
    problem = transcription.stagewise_nlp(task)
    # The optimum does not depend on the starting point: no derivative flows into the guess.
    Z0, theta0 = jax.lax.stop_gradient(transcription.to_variables(task, guess))
    solution = sensitivity.differentiable_solve(problem, Z0, theta0, options, multipliers, bound_multipliers, settings)
    return task_solution(task, problem, solution)


def solve_task_differentiable(task, guess=None, options=DEFAULT_OPTIONS, warm_start=None,
                              settings=sensitivity.Options()):
    """``optimise.solve_task`` whose ``TaskSolution`` is differentiable (reverse mode) with
    respect to the float leaves of ``task``; integer and static fields get no cotangent.

    task: a ``Task``; guess: a ``Trajectory`` (default: the published initial guess; no
    derivative flows into it); options: solver ``interior_point.Options``; warm_start: a previous
    ``TaskSolution`` of a task of the same structure (its trajectory is the default guess, its
    multipliers start the solve, with ``optimise.WARM_START``'s barrier settings); settings:
    ``sensitivity.Options``. Differentiable outputs: ``trajectory``, ``solution.Z``,
    ``solution.theta``, ``solution.multipliers``, ``solution.objective`` and the violations;
    the other statistics carry no gradient.
    """
    guess, options, multipliers, bound_multipliers = prepare(task, guess, options, warm_start)
    return _solve(task, guess, options, settings, multipliers, bound_multipliers)


@compilation.jit
def _gradient(task, solution, cotangent):
    problem, pull_task = jax.vjp(transcription.stagewise_nlp, task)
    nlp_bar, diagnostics = sensitivity.vjp(problem, solution, *cotangent)
    return pull_task(nlp_bar)[0], diagnostics


def gradient(task, result, loss):
    """d loss / d task at a solved task, by implicit differentiation at ``result`` (no re-solve).

    task: the ``Task`` that was solved; result: its ``TaskSolution`` (``optimise.solve_task``,
    converged); loss(task, trajectory) → () a differentiable scalar of the optimal
    ``Trajectory`` that may also read the task. Returns (value, task_bar, diagnostics):
    task_bar has the structure of ``task`` with d loss / d leaf on every float leaf (weights,
    targets, bounds, the model's numbers; float0 on integer leaves), the explicit dependence of
    ``loss`` on ``task`` included; diagnostics: ``sensitivity.Diagnostics`` (check
    ``diagnostics.reliable()``: it is False when the solve did not converge or the adjoint KKT
    system could not be solved accurately, and then task_bar is not a derivative).
    """
    solution = result.solution

    def of(Z, theta, task):
        return loss(task, transcription.to_trajectory(task, Z, theta))

    value, (Z_bar, theta_bar, direct) = jax.value_and_grad(of, argnums=(0, 1, 2), allow_int=True)(
        solution.Z, solution.theta, task)
    implicit, diagnostics = _gradient(task, solution, (Z_bar, theta_bar))
    total = jax.tree.map(lambda a, b: a if a.dtype == jax.dtypes.float0 else a + b, implicit, direct)
    return value, total, diagnostics
