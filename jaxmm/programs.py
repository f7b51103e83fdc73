"""Internal: the compiled programs of a task's solve, for ``solve``, ``batch``, the command line
and the diagnostics in ``tools/``. The public way to solve is ``jaxmm.solve.solve_task``.

A solve is three programs: ``start``, ``advance`` to an iteration count, ``finish``. Run one
after the other (or in slices, by ``solver.stopping.run``), every solve of a problem structure
(robot, knot count, integration rule, options) shares the one heavy program, ``advance``,
whatever its start (cold, warm, another scaling), its numbers (targets, weights, bounds), its
time budget or its interrupts. ``solve_program`` is the whole solve as one traceable function
(what ``sharded_batch_solve`` maps or vmaps over the instances of each device);
``compile_solve`` compiles the three programs ahead of time;
``differentiable_solve`` and ``adjoint`` are the implicitly differentiated solve and the adjoint
solve at a found optimum (``solver.sensitivity``).
"""

import concurrent.futures
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm import compilation, stagewise
from jaxmm.solver import interior_point as ip
from jaxmm.solver import sensitivity, stopping
from jaxmm.tasks import initial_guess
from jaxmm.transcription import nlp as transcription
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
# The settings with which the exact task (``tasks.exact_complementarity``) is solved from a guess:
# the relaxation homotopy κ_σ = 1e-3 (Scholtes' relaxation driven by μ), with μ, and so σ,
# multiplied by κ_μ = 0.7 from one barrier problem to the next (θ_μ = 1) instead of IPOPT's
# superlinear decrease (0.2, 1.5), which takes σ from 10 to 0.28 N m in one step on walk-to-fly
# (docs/design-decisions.md, "The exact task's barrier schedule"); the command line's and the
# benchmarks' --exact take them.
EXACT_OPTIONS = dataclasses.replace(DEFAULT_OPTIONS, relaxation=1e-3, barrier_factor=0.7, barrier_power=1.0)


# A warm start begins near the bounds the previous solution touches, with a small barrier.
WARM_START = dict(barrier0=1e-6, bound_push=1e-6)


def task_solution(task, nlp, solution, residuals=None):
    """The ``TaskSolution`` of ``task`` for a ``Solution`` of its stage-wise ``nlp``;
    ``residuals``: the NLP's residuals at the solution when they are at hand."""
    r = stagewise.residuals(nlp, solution.Z, solution.theta) if residuals is None else residuals
    outside = dataclasses.replace(
        r, path_equality=jnp.abs(r.path_equality), transition_equality=jnp.abs(r.transition_equality),
        path_inequality=ip.outside(r.path_inequality, nlp.path_lower, nlp.path_upper),
        transition_inequality=ip.outside(r.transition_inequality, nlp.transition_lower, nlp.transition_upper),
    )
    families = {name: jnp.max(v, initial=0.0) for name, v in transcription.split_families(task, outside).items()}
    return TaskSolution(transcription.to_trajectory(task, solution.Z, solution.theta), solution, families)


def solve_program(task, guess, options, multipliers=None, bound_multipliers=None, scaling=None):
    """The whole solve of ``task`` from ``guess`` as one traceable function → ``TaskSolution``
    (what a mesh's devices run; ``solve_task`` runs it as the three compiled programs below)."""
    nlp = transcription.stagewise_nlp(task)
    Z0, theta0 = transcription.to_variables(task, guess)
    return task_solution(task, nlp, ip.solve(nlp, Z0, theta0, options, multipliers, bound_multipliers, scaling))


@compilation.jit(static_argnames="options")
def start(task, guess, options, multipliers, bound_multipliers, scaling=None):
    """The solver's ``State`` at ``guess`` (``ip.start``)."""
    Z0, theta0 = transcription.to_variables(task, guess)
    return ip.start(transcription.stagewise_nlp(task), Z0, theta0, options, multipliers, bound_multipliers, scaling)


@compilation.jit(static_argnames="options")
def advance(task, state, options, until):
    """``state`` iterated until it stops or reaches iteration ``until`` (``ip.advance``)."""
    return ip.advance(transcription.stagewise_nlp(task), state, options, until)


@compilation.jit
def finish(task, state, stopped):
    """The ``TaskSolution`` of a last ``state``; ``stopped``: the status of a solve cut short."""
    nlp = transcription.stagewise_nlp(task)
    return task_solution(task, nlp, ip.finish(nlp, state, stopped), state.residuals)


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
        # NumPy: a jnp check of each leaf would compile one program per operation and shape.
        if not isinstance(leaf, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(leaf))):
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


def run(state, advance, finish, max_iterations, time_budget, interruptible):
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
    started, advanced, finished = compiled_programs(task, guess, options, multipliers, bound_multipliers)
    iterating = ip.iteration_options(options)

    def solve(other=None):
        if other is not None:
            check_guess(task, other)
        state = started(task, guess if other is None else other, options, multipliers, bound_multipliers)
        return run(state, lambda s, until: advanced(task, s, iterating, until),
                   lambda s, stopped: finished(task, s, stopped), iterating.max_iterations, time_budget, interruptible)

    return solve


def compiled_programs(task, guess, options, multipliers, bound_multipliers, scaling=None):
    """(start, advance, finish) compiled for these arguments (``compilation.Program``s; advance
    takes ``ip.iteration_options(options)``), loaded where a cache has them. ``start`` and
    ``finish`` compile in a second thread while this one traces and lowers ``advance``: XLA
    compiles without holding Python's lock, so their compiles hide behind the tracing."""
    state = jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype),
                         start.eval_shape(task, guess, options, multipliers, bound_multipliers, scaling))
    iterating = ip.iteration_options(options)
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        started = pool.submit(start.compiled, task, guess, options, multipliers, bound_multipliers, scaling)
        finished = pool.submit(finish.compiled, task, state, int(ip.Status.MAX_ITERATIONS))
        advanced = advance.compiled(task, state, iterating, iterating.max_iterations)
        return started.result(), advanced, finished.result()


@compilation.jit(static_argnames=("options", "settings"))
def differentiable_solve(task, guess, options, settings, multipliers, bound_multipliers):
    """The solve of ``task`` whose ``TaskSolution`` has implicit reverse-mode derivatives with
    respect to ``task`` (``sensitivity.differentiable_solve``)."""
    problem = transcription.stagewise_nlp(task)
    # The optimum does not depend on the starting point: no derivative flows into the guess.
    Z0, theta0 = jax.lax.stop_gradient(transcription.to_variables(task, guess))
    solution = sensitivity.differentiable_solve(problem, Z0, theta0, options, multipliers, bound_multipliers, settings)
    return task_solution(task, problem, solution)


@compilation.jit
def adjoint(task, solution, cotangent):
    """(task_bar, diagnostics): the cotangent (Z_bar, theta_bar) of a solved task's variables
    pulled back to ``task`` by one adjoint KKT solve at ``solution`` (``sensitivity.vjp``)."""
    problem, pull_task = jax.vjp(transcription.stagewise_nlp, task)
    nlp_bar, diagnostics = sensitivity.vjp(problem, solution, *cotangent)
    return pull_task(nlp_bar)[0], diagnostics


# ------------------------------------------------------------------------------ batches


def over(one, vectorised):
    """one(task, x) over batched (tasks, xs): vmapped (``vectorised``: the instances advance
    together, every kernel batched) or ``lax.map``ped (one instance after another, each running
    only its own iterations, every kernel unbatched)."""
    if vectorised:
        return jax.vmap(one)
    return lambda tasks, xs: jax.lax.map(lambda pair: one(*pair), (tasks, xs))


def instances(options, vectorised):
    """The solve of a batch of (task, guess) instances (see ``over``)."""
    return over(lambda task, guess: solve_program(task, guess, options), vectorised)


@functools.partial(jax.jit, static_argnames=("options", "mesh", "vectorised"))
def sharded_batch_solve(tasks, guesses, options, mesh, vectorised):
    """``solve_program`` over a batched task and its guesses (see ``instances``), the instances
    split over the devices of ``mesh``: each device
    solves its own B / D instances (``jax.shard_map``), its loops stopping when its own
    instances stop. The instances are independent, so there is no collective at all (an
    SPMD-partitioned vmap would all-reduce "any instance still running" on every trip of every
    while loop: Newton, line search, inertia correction)."""
    spec = jax.sharding.PartitionSpec("batch")
    return jax.shard_map(instances(options, vectorised), mesh=mesh, in_specs=(spec, spec), out_specs=spec,
                         check_vma=False)(tasks, guesses)
