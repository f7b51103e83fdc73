"""Solve a task: the task's stage-wise NLP handed to the interior-point solver, and the answer
brought back as a trajectory in physical units.

This is the public boundary where compilation happens: ``solve_task`` jit-compiles one solve per
problem structure (robot, knot count, integration rule, options) and reuses it for every task of
that structure, whatever its numbers (targets, weights, bounds).
"""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmm import compilation
from jaxmm.solver import interior_point as ip
from jaxmm.solver import stopping
from jaxmm.tasks import initial_guess
from jaxmm.transcription import nlp as transcription
from jaxmm.transcription import stagewise
from jaxmm.transcription.problem import Task
from jaxmm.transcription.variables import Trajectory


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TaskSolution:
    """A solved task: the optimal ``trajectory`` (physical units), the solver's ``solution``
    (scaled variables, multipliers, status, statistics, history; see ``ip.Solution``) and the
    largest violation of each constraint family (``{family: ()}``, docs/formulation.md's names)."""

    trajectory: Trajectory
    solution: ip.Solution
    violation_per_family: dict

    @property
    def status(self):
        return ip.Status(int(self.solution.status))


DEFAULT_OPTIONS = ip.Options()


# A warm start begins near the bounds the previous solution touches, with a small barrier.
WARM_START = dict(barrier0=1e-6, bound_push=1e-6)


def task_solution(task, nlp, solution):
    """The ``TaskSolution`` of ``task`` for a ``Solution`` of its stage-wise ``nlp``."""
    r = stagewise.residuals(nlp, solution.Z, solution.theta)
    outside = dataclasses.replace(
        r, path_equality=jnp.abs(r.path_equality), transition_equality=jnp.abs(r.transition_equality),
        path_inequality=ip.outside(r.path_inequality, nlp.path_lower, nlp.path_upper),
        transition_inequality=ip.outside(r.transition_inequality, nlp.transition_lower, nlp.transition_upper),
    )
    families = {name: jnp.max(v, initial=0.0) for name, v in transcription.split_families(task, outside).items()}
    return TaskSolution(transcription.to_trajectory(task, solution.Z, solution.theta), solution, families)


def solve_program(task, guess, options, multipliers=None, bound_multipliers=None, scaling=None):
    """The whole solve of ``task`` from ``guess`` as one traceable function → ``TaskSolution``
    (what ``batch`` vmaps; ``solve_task`` runs it as the three compiled slices below)."""
    nlp = transcription.stagewise_nlp(task)
    Z0, theta0 = transcription.to_variables(task, guess)
    return task_solution(task, nlp, ip.solve(nlp, Z0, theta0, options, multipliers, bound_multipliers, scaling))


# The solve in three programs: start, advance to an iteration count, finish. Run one after the
# other (or in slices, by stopping.run), every solve of a structure shares the one heavy program,
# advance, whatever its start (cold, warm, another scaling), its time budget or its interrupts.
@compilation.jit(static_argnames="options")
def _start(task, guess, options, multipliers, bound_multipliers, scaling=None):
    Z0, theta0 = transcription.to_variables(task, guess)
    return ip.start(transcription.stagewise_nlp(task), Z0, theta0, options, multipliers, bound_multipliers, scaling)


@compilation.jit(static_argnames="options")
def _advance(task, state, options, until):
    return ip.advance(transcription.stagewise_nlp(task), state, options, until)


@compilation.jit
def _finish(task, state, stopped):
    nlp = transcription.stagewise_nlp(task)
    return task_solution(task, nlp, ip.finish(nlp, state, stopped))


def check_guess(task, guess, label="guess"):
    """Raise a ValueError/TypeError naming the problem unless ``guess`` is a ``Trajectory`` with
    the shapes ``task`` needs (those of ``tasks.initial_guess(task)``), real dtypes and, when
    given by value (not traced), finite entries."""
    if not isinstance(guess, Trajectory):
        raise TypeError(f"{label} must be a Trajectory (see tasks.initial_guess), got {type(guess).__name__}")
    expected = jax.eval_shape(initial_guess, task)
    leaves, treedef = jax.tree_util.tree_flatten_with_path(guess)
    if treedef != jax.tree.structure(expected):
        raise ValueError(f"{label} does not have the structure of this task's trajectories")
    for (path, leaf), want in zip(leaves, jax.tree.leaves(expected)):
        where = f"{label}{jax.tree_util.keystr(path)}"
        if jnp.shape(leaf) != want.shape:
            raise ValueError(f"{where} has shape {jnp.shape(leaf)}; the task ({task.n_knots} knots) needs {want.shape}")
        dtype = jnp.result_type(leaf)
        if not (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)):
            raise TypeError(f"{where} has dtype {dtype}; a real (float) array is needed")
        if not isinstance(leaf, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(leaf))):
            raise ValueError(f"{where} has non-finite entries (NaN or inf)")


def prepare(task, guess=None, options=DEFAULT_OPTIONS, warm_start=None):
    """The arguments of the compiled solve, (guess, options, multipliers, bound_multipliers),
    after checking them: ``guess`` defaults to the warm start's trajectory, else to the
    published initial guess; a warm start brings its multipliers and ``WARM_START``'s barrier
    settings."""
    if not isinstance(task, Task):
        raise TypeError(f"task must be a Task (see tasks.scenario, tasks.build_task), got {type(task).__name__}")
    if not isinstance(options, ip.Options):
        raise TypeError(f"options must be interior_point.Options, got {type(options).__name__}")
    multipliers = bound_multipliers = None
    if warm_start is not None:
        if not isinstance(warm_start, TaskSolution):
            raise TypeError(f"warm_start must be a TaskSolution, got {type(warm_start).__name__}")
        if guess is not None:  # otherwise the check of the guess below is this one
            check_guess(task, warm_start.trajectory, "warm_start.trajectory")
        guess = warm_start.trajectory if guess is None else guess
        options = dataclasses.replace(options, **WARM_START)
        multipliers, bound_multipliers = warm_start.solution.multipliers, warm_start.solution.bound_multipliers
    guess = initial_guess(task) if guess is None else guess
    check_guess(task, guess)
    return guess, options, multipliers, bound_multipliers


def solve_task(task, guess=None, options=DEFAULT_OPTIONS, warm_start=None, same_scaling=False, *,
               time_budget=None, interruptible=False):
    """Optimise ``task`` (a ``Task``) from ``guess`` (a ``Trajectory``; default: the published
    initial guess). Returns a ``TaskSolution``; check ``.status`` and ``jaxmm.analysis.validate``.

    warm_start: a previous ``TaskSolution`` of a task with the same structure (say, other
    weights or targets): its trajectory becomes the default guess and its multipliers start the
    solve, with the barrier parameter and bound push of ``WARM_START``.

    The default tolerances: constraint violation ≤ 1e-6 (100× tighter than the paper's IPOPT
    ``constr_viol_tol``) and scaled stationarity ≤ 1e-4 (the paper's IPOPT ``tol``).
    same_scaling: solve in the warm start's cost and row scaling instead of the one computed at
    the new starting point, so that the answers to nearby tasks differ only through the task
    (what finite differences of re-solves need: the barrier problem at μ > 0 depends on the
    cost factor, which follows the weights).

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
    guess, options, multipliers, bound_multipliers = prepare(task, guess, options, warm_start)
    stopping.check_budget(time_budget)
    scaling = None
    if same_scaling:
        if warm_start is None:
            raise ValueError("same_scaling=True needs a warm_start (whose scaling to keep)")
        scaling = warm_start.solution.scaling
    state = _start(task, guess, options, multipliers, bound_multipliers, scaling)
    options = ip.iteration_options(options)
    return _run(state, lambda s, until: _advance(task, s, options, until), lambda s, stopped: _finish(task, s, stopped),
                options.max_iterations, time_budget, interruptible)


def _run(state, advance, finish, max_iterations, time_budget, interruptible):
    """A started solve to its end: one call of ``advance`` when nothing needs checking between
    iterations, else slices under ``stopping.run``."""
    if time_budget is None and not interruptible:
        return finish(advance(state, max_iterations), int(ip.Status.MAX_ITERATIONS))
    return stopping.run(state, advance, finish, max_iterations, time_budget=time_budget, interruptible=interruptible)


def compile_solve(task, guess=None, options=DEFAULT_OPTIONS, warm_start=None, *, time_budget=None,
                  interruptible=False):
    """Compile the solve of ``task`` ahead of time, as ``solve_task`` would run it, without
    running it: returns ``run(guess=None)`` → ``TaskSolution``, from the compiled guess or from
    another of the same shapes (checked as ``solve_task`` checks it). For callers that
    report (or time) compiling apart from solving; the compiled program is also the one
    ``solve_task`` reuses for every task of the same structure. time_budget, interruptible: as
    for ``solve_task`` (its three programs are compiled here, so the first slice of a sliced
    solve includes no compiling)."""
    guess, options, multipliers, bound_multipliers = prepare(task, guess, options, warm_start)
    stopping.check_budget(time_budget)
    start = _start.lower(task, guess, options, multipliers, bound_multipliers).compile()
    state = jax.eval_shape(lambda *arguments: _start(*arguments[:2], options, *arguments[2:]), task, guess, multipliers,
                           bound_multipliers)
    options = ip.iteration_options(options)
    advance = _advance.lower(task, state, options, options.max_iterations).compile()
    finish = _finish.lower(task, state, int(ip.Status.MAX_ITERATIONS)).compile()

    def run(other=None):
        if other is not None:
            check_guess(task, other)
        state = start(task, guess if other is None else other, multipliers, bound_multipliers)
        return _run(state, lambda s, until: advance(task, s, until), lambda s, stopped: finish(task, s, stopped),
                    options.max_iterations, time_budget, interruptible)

    return run
