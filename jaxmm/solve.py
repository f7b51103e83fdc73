"""Solve a task, and differentiate its optimum: the task's stage-wise NLP handed to the
interior-point solver, and the answer brought back as a trajectory in physical units.

``solve_task`` is the one way to solve a task. It jit-compiles one solve per problem structure
(robot, knot count, integration rule, options) and reuses it for every task of that structure,
whatever its numbers (targets, weights, bounds). With ``differentiable=True`` its
``TaskSolution`` is differentiable (reverse mode) with respect to every float leaf of the
``Task`` (cost weights, targets x₀ and x_N, the mid-horizon height, jet coefficients, bounds, the
robot model's numbers), by implicit differentiation of the KKT conditions at the solution
(``jaxmm.solver.sensitivity``), never through the solver's iterations:

    def impulse(weights):
        task = dataclasses.replace(base, weights=weights)
        result = solve_task(task, warm_start=previous, differentiable=True)
        knots = result.trajectory.knots
        return jnp.sum(knots.thrust[:-1]) * result.trajectory.total_time / task.n_intervals

    jax.grad(impulse)(base.weights)

``gradient`` differentiates a solution already found without solving again: one adjoint solve
at that solution, compiled apart from the solver. ``solve_elastic`` solves a task to exact
contact complementarity: ``solve_task``, then the elastic-mode continuation on the slack weight.

The derivative is that of the local optimum the solver found, with its active set held fixed
(smoothed by the final barrier parameter, see ``jaxmm.solver.sensitivity``): it is the true
derivative where the active set does not change under the perturbation. Gradients are NaN when
the solve did not converge or the KKT system could not be solved accurately (see
``sensitivity.Options``).
"""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmm import programs
from jaxmm.analysis.validation import complementarity
from jaxmm.programs import DEFAULT_OPTIONS, WARM_START, TaskSolution
from jaxmm.solver import interior_point as ip
from jaxmm.solver import sensitivity, stopping
from jaxmm.tasks import with_slack_penalty
from jaxmm.transcription import nlp as transcription

__all__ = ["DEFAULT_OPTIONS", "HANDOVER", "WARM_START", "ElasticSolution", "TaskSolution", "gradient", "solve_elastic",
           "solve_task"]


def _differentiable(task, guess, options, warm_start, settings, time_budget, interruptible, same_scaling):
    if time_budget is not None or interruptible or same_scaling:
        raise ValueError("a differentiable solve is one call: it takes no time_budget, interruptible or same_scaling")
    settings = sensitivity.Options() if settings is True else settings
    if not isinstance(settings, sensitivity.Options):
        raise TypeError(f"differentiable must be a bool or sensitivity.Options, got {type(settings).__name__}")
    guess, options, multipliers, bound_multipliers = programs.prepare(task, guess, options, warm_start)
    return programs.differentiable_solve(task, guess, options, settings, multipliers, bound_multipliers)


def solve_task(task, guess=None, options=DEFAULT_OPTIONS, warm_start=None, same_scaling=False, *,
               differentiable=False, time_budget=None, interruptible=False):
    """Optimise ``task`` (a ``Task``) from ``guess`` (a ``Trajectory``; default: the published
    initial guess). Returns a ``TaskSolution``; check ``.status`` and ``jaxmm.analysis.validate``.

    options: solver ``interior_point.Options`` (static: another value compiles another solve).
    The default tolerances: constraint violation ≤ 1e-6 (100× tighter than the paper's IPOPT
    ``constr_viol_tol``) and scaled stationarity ≤ 1e-4 (the paper's IPOPT ``tol``).

    warm_start: a previous ``TaskSolution`` of a task with the same structure (say, other
    weights or targets): its trajectory becomes the default guess and its multipliers start the
    solve, with the barrier parameter and bound push of ``WARM_START``.
    same_scaling: solve in the warm start's cost and row scaling instead of the one computed at
    the new starting point, so that the answers to nearby tasks differ only through the task
    (what finite differences of re-solves need: the barrier problem at μ > 0 depends on the
    cost factor, which follows the weights).

    differentiable: True (or a ``sensitivity.Options``) makes the returned ``trajectory``,
    ``solution.Z``, ``solution.theta``, ``solution.multipliers``, ``solution.objective`` and the
    violations differentiable in reverse mode with respect to the float leaves of ``task``
    (integer and static fields get no cotangent; no derivative flows into the guess); the other
    statistics carry no gradient. Such a solve is one XLA call.

    time_budget: seconds [s] of iterating after the first iteration (which includes compiling,
    on a structure's first solve); when they run out the solve stops with status
    ``TIME_LIMIT`` and its last iterate. interruptible: the first Ctrl-C (SIGINT, a notebook's
    interrupt) stops the solve the same way with status ``INTERRUPTED``; a second one raises
    KeyboardInterrupt. Both run the solve in slices of about half a second
    (``jaxmm.solver.stopping``); without them (the default) the iterations are one XLA call,
    which a Ctrl-C cannot stop.

    Raises TypeError/ValueError naming the problem for a guess or warm start of the wrong type,
    shape or dtype, or with non-finite entries, and for a time budget that is not positive.
    """
    if differentiable is not False:
        return _differentiable(task, guess, options, warm_start, differentiable, time_budget, interruptible,
                               same_scaling)
    return _iterate(task, guess, options, warm_start, same_scaling, time_budget, interruptible)


def _iterate(task, guess, options, warm_start, same_scaling, time_budget, interruptible, iterations=None):
    """``solve_task``'s solve, stopped with status ``MAX_ITERATIONS`` after ``iterations``
    (default options.max_iterations; a traced count: the compiled ``advance`` serves every cap)."""
    guess, options, multipliers, bound_multipliers = programs.prepare(task, guess, options, warm_start)
    iterations = options.max_iterations if iterations is None else min(iterations, options.max_iterations)
    stopping.check_budget(time_budget)
    scaling = None
    if same_scaling:
        if warm_start is None:
            raise ValueError("same_scaling=True needs a warm_start (whose scaling to keep)")
        scaling = warm_start.solution.scaling
    started, advanced, finished = programs.compiled_programs(task, guess, options, multipliers, bound_multipliers,
                                                             scaling)
    state = started(task, guess, options, multipliers, bound_multipliers, scaling)
    options = ip.iteration_options(options)
    return programs.run(state, lambda s, until: advanced(task, s, options, until),
                        lambda s, stopped: finished(task, s, stopped), iterations, time_budget, interruptible)


def gradient(task, result, loss):
    """d loss / d task at a solved task, by implicit differentiation at ``result`` (no re-solve).

    task: the ``Task`` that was solved; result: its ``TaskSolution`` (``solve_task``,
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
    implicit, diagnostics = programs.adjoint(task, solution, (Z_bar, theta_bar))
    total = jax.tree.map(lambda a, b: a if a.dtype == jax.dtypes.float0 else a + b, implicit, direct)
    return value, total, diagnostics


@dataclasses.dataclass(frozen=True)
class ElasticSolution:
    """The answer of ``solve_elastic``: ``task``, the task its last converged stage solved (the
    given one with its slack weight raised), and ``result``, that stage's ``TaskSolution``
    (what ``validate``, ``gradient`` and ``io.save`` take with ``task``). Per stage, in order
    (the smooth start's first when there is one, then ``solve_task``'s solve of the published
    penalty, then the raises): ``penalties`` ("squared" or "linear"), ``weights`` (the slack
    weight on that penalty), ``iterations``, ``statuses`` (``ip.Status``) and ``products`` (the
    largest of ``complementarity``'s normal and planar products [N m]; NaN for a stage that did
    not converge)."""

    task: object
    result: TaskSolution
    penalties: tuple
    weights: tuple
    iterations: tuple
    statuses: tuple
    products: tuple

    @property
    def status(self):
        return self.result.status

    @property
    def total_iterations(self):
        return sum(self.iterations)


# The published penalty's stage after a converged smooth start: a cold start (the squared stage's
# multipliers belong to another problem) at a barrier parameter below the default 0.1, so that
# the start from a near-optimal point does not first move away from it.
HANDOVER = dict(barrier0=1e-3)


def _stage(penalty, weight, result):
    converged = result.status == ip.Status.CONVERGED
    product = _largest_product(result.trajectory) if converged else float("nan")
    return penalty, weight, int(result.solution.iterations), result.status, product


def _largest_product(trajectory):
    measure = complementarity(trajectory)
    return max(measure["normal"], measure["planar"])


def _smooth_start(task, guess, options, iterations):
    """The smooth start's stage and the published stage's (guess, options): the squared stage's
    trajectory and ``HANDOVER`` where it converged, else the given ones."""
    smooth = with_slack_penalty(task, "squared")
    result = _iterate(smooth, guess, options, None, False, None, False, iterations)
    stage = _stage("squared", float(smooth.weights.complementarity_slack_squared), result)
    if result.status != ip.Status.CONVERGED:
        return stage, guess, options
    return stage, result.trajectory, dataclasses.replace(options, **HANDOVER)


def solve_elastic(task, guess=None, options=DEFAULT_OPTIONS, *, tolerance=1e-6, factor=10.0, max_stages=4,
                  stage_iterations=1500, smooth_start=False, smooth_iterations=120):
    """Solve ``task`` to exact contact complementarity: ``solve_task(task, guess, options)``,
    then, while a product f_z c_z or |f_z Δc_xy| (eq. 20, 21) is above ``tolerance`` [N m], the
    same task with its slack weight w_complementarity_slack × ``factor``, warm-started from the
    last answer, up to ``max_stages`` raises of at most ``stage_iterations`` iterations each.
    Returns an ``ElasticSolution``.

    The published relaxation pays for the slacks ε ≥ f_z c_z, |f_z Δc| in the cost (eq. 32): an
    ℓ1 penalty, which is exact (Anitescu 2005, the elastic mode for MPCCs): once w exceeds the
    complementarity rows' multipliers the penalised optimum has ε = 0, so that a finite number
    of raises reaches it. Each stage is a short warm-started solve, and every stage shares one
    compiled solve (weights are data). With the published slack weight, a task whose optimum
    buys force on a corner in the air (``validate`` fails) is moved to a physical one nearby.

    smooth_start: first solve the task with its slack weight on Σ ε² (``tasks.with_slack_penalty``:
    smooth, its slacks stay off the degenerate vertex ε = 0 of the ℓ1 relaxation), for at most
    ``smooth_iterations``; where that converges, the published penalty's stage starts from its
    trajectory (cold, ``HANDOVER``), else from ``guess`` as without it. It pays on tasks whose
    ℓ1 solve crawls at that vertex (the take-off: docs/benchmarks.md), not on the jump, whose
    squared stage does not converge.

    A stage that does not converge (``MAX_ITERATIONS`` past ``stage_iterations``) ends the
    continuation: the result is then the last converged stage, whose product (above
    ``tolerance``) precedes the failed stage's NaN in ``products``. Raises
    ValueError for a tolerance, factor or stage count out of range, TypeError as ``solve_task``.
    """
    counts = all(isinstance(n, int) for n in (max_stages, stage_iterations, smooth_iterations))
    positive = min(stage_iterations, smooth_iterations) > 0 if counts else False
    if not (tolerance > 0 and factor > 1 and counts and max_stages >= 0 and positive):
        raise ValueError(f"need tolerance > 0, factor > 1, an integer max_stages ≥ 0 and stage_iterations, "
                         f"smooth_iterations > 0; got {tolerance!r}, {factor!r}, {max_stages!r}, {stage_iterations!r}, "
                         f"{smooth_iterations!r}")
    stages = []
    if smooth_start:
        smooth, guess, options = _smooth_start(task, guess, options, smooth_iterations)
        stages.append(smooth)
    result = solve_task(task, guess, options)
    weight = float(task.weights.complementarity_slack)
    stages.append(_stage("linear", weight, result))
    for _ in range(max_stages):
        if result.status != ip.Status.CONVERGED or stages[-1][4] <= tolerance:
            break
        weight *= factor
        # The same leaf type as a scenario's weights (a float64 array): the stage reuses the compiled solve.
        weights = dataclasses.replace(task.weights, complementarity_slack=jnp.asarray(weight, dtype=float))
        raised = dataclasses.replace(task, weights=weights)
        stage = _iterate(raised, None, options, result, False, None, False, stage_iterations)
        stages.append(_stage("linear", weight, stage))
        if stage.status != ip.Status.CONVERGED:
            break
        task, result = raised, stage
    return ElasticSolution(task, result, *zip(*stages))
