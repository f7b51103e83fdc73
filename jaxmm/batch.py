"""Batched solves: many initial guesses (multi-start) or many tasks of one structure, run by the
strategy that pays on the backend (``jaxmm.schedule``: one compiled solve after another on a
CPU, refilled vmapped slots on an accelerator, or split over the devices of a mesh); perturbed
initial guesses; and a summary that ranks the answers and groups them by contact schedule.

Under ``vmap`` the solver's loops run while any slot needs them, and batched and unbatched XLA
kernels round differently (1e-16 at the first iteration), which a nonconvex solve can amplify
over hundreds of iterations into a few iterations more or less and a different point within the
solver's tolerance: a vmapped instance's answer is its single solve's up to that rounding.

A batch is any pytree with a leading batch axis on every leaf: guesses are a ``Trajectory`` of
leaves (B, N + 1, ...) and total time (B,); tasks a ``Task`` whose array leaves (targets,
weights, bounds, the model's numbers) are (B, ...), with its static structure (robot topology,
knot count, options) shared; the answer a ``TaskSolution`` with every leaf (B, ...). A
multi-start batch broadcasts its task, so multi-start and multi-task batches share one
compilation.
"""

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm import analysis, programs, schedule
from jaxmm.solver import interior_point as ip
from jaxmm.solver import stopping
from jaxmm.tasks import initial_guess
from jaxmm.transcription.constraints import variable_bounds
from jaxmm.transcription.problem import Task
from jaxmm.transcription.variables import Trajectory

# ----------------------------------------------------------------------------------- batches


def _static_differences(a, b, path):
    """The static (compile-time) fields in which two pytrees of dataclasses differ, as
    "path: value vs value" strings."""
    if not (dataclasses.is_dataclass(a) or dataclasses.is_dataclass(b)):
        return []  # array leaves: their values may differ
    if type(a) is not type(b):
        return [f"{path}: {type(a).__name__} vs {type(b).__name__}"]
    found = []
    for field in dataclasses.fields(a):
        x, y = getattr(a, field.name), getattr(b, field.name)
        here = f"{path}.{field.name}"
        if field.metadata.get("static", False):
            if x != y:
                shown = (repr(x), repr(y))
                found.append(f"{here}: " + (" vs ".join(shown) if max(map(len, shown)) <= 60 else "differs"))
        else:
            found.extend(_static_differences(x, y, here))
    return found


def _stack(items, kind, label):
    """Stack pytrees of type ``kind`` with equal structure and leaf shapes along a new leading
    axis. label names them in errors ("task", "guess")."""
    if not isinstance(items, Sequence):
        raise TypeError(f"expected a list of {kind.__name__}s to stack, got {type(items).__name__}")
    if not items:
        raise ValueError(f"cannot stack an empty list (no {label} given)")
    for i, item in enumerate(items):
        if not isinstance(item, kind):
            raise TypeError(f"{label} {i} is a {type(item).__name__}, not a {kind.__name__}")
    first, first_def = jax.tree_util.tree_flatten_with_path(items[0])
    for i, item in enumerate(items[1:], start=1):
        leaves, treedef = jax.tree_util.tree_flatten_with_path(item)
        if treedef != first_def:
            differences = _static_differences(items[0], item, label) or ["the pytree structure"]
            raise ValueError(f"{label} {i} cannot be batched with {label} 0: they differ in their static "
                             f"structure ({'; '.join(differences)})")
        for (path, a), (_, b) in zip(first, leaves):
            if jnp.shape(a) != jnp.shape(b):
                raise ValueError(f"{label} {i} cannot be batched with {label} 0: {label}"
                                 f"{jax.tree_util.keystr(path)} has shape {jnp.shape(b)}, not {jnp.shape(a)}")
    return jax.tree.map(_stack_leaves, *items)


def _stack_leaves(*leaves):
    # On the host when the leaves are values: one transfer per leaf instead of one compiled
    # stack per leaf shape (hundreds for a Task, minutes on simulated multi-device CPUs).
    if any(isinstance(leaf, jax.core.Tracer) for leaf in leaves):
        return jnp.stack(leaves)
    return jnp.asarray(np.stack([np.asarray(leaf) for leaf in leaves]))


def broadcast_task(task, size):
    """``task`` repeated ``size`` times as a batched ``Task`` (every array leaf (size, ...)), with
    the leaf types of ``stack_tasks`` (no weak types: a weakly typed leaf would compile a second
    batch solve)."""
    return jax.tree.map(lambda leaf: jnp.broadcast_to(jnp.asarray(leaf, dtype=jnp.result_type(leaf)),
                                                      (size,) + jnp.shape(leaf)), task)


def stack_tasks(tasks):
    """One batched ``Task`` from a list of B tasks of equal structure (same robot topology, knot
    count, options and name; their numbers may differ): every array leaf gets a leading (B,)
    axis. Raises ValueError naming the first field that differs in structure or shape."""
    return _stack(tasks, Task, "task")


def stack_trajectories(trajectories):
    """One batched ``Trajectory`` (leaves (B, N + 1, ...), total time (B,)) from a list of B
    trajectories with the same knot count and robot layout."""
    return _stack(trajectories, Trajectory, "guess")


def batch_size(batch):
    """B, the leading axis shared by every leaf of a batched pytree (``Task``, ``Trajectory``,
    ``TaskSolution``). Raises ValueError when the leaves disagree or one is a scalar."""
    leaves = jax.tree_util.tree_flatten_with_path(batch)[0]
    if not leaves:
        raise ValueError("a batch needs at least one array leaf")
    sizes = {}
    for path, leaf in leaves:
        shape = jnp.shape(leaf)
        if not shape:
            raise ValueError(f"{jax.tree_util.keystr(path)} is a scalar: not batched (stack instances with "
                             "stack_tasks or stack_trajectories)")
        sizes.setdefault(shape[0], jax.tree_util.keystr(path))
    if len(sizes) > 1:
        raise ValueError("the leaves of the batch have different leading sizes: "
                         + ", ".join(f"{path} {size}" for size, path in sizes.items()))
    return next(iter(sizes))


def instance(batch, i):
    """Instance i of a batched pytree (the leading axis removed from every leaf): a
    ``TaskSolution`` of ``solve_batch``, a guess of ``sample_guesses``, a task of ``stack_tasks``."""
    size = batch_size(batch)
    if not isinstance(i, (int, np.integer)) or not -size <= i < size:
        raise IndexError(f"instance {i!r} is out of range for a batch of {size}")
    return jax.tree.map(lambda leaf: leaf[i], batch)


def _batched_guesses(guesses):
    return stack_trajectories(guesses) if isinstance(guesses, Sequence) else guesses


def _check_shapes(trajectory, expected, batch, label):
    """Every leaf of ``trajectory`` has the shape batch + that of ``expected`` (one instance's
    ShapeDtypeStructs); label names it in the error."""
    for (path, leaf), want in zip(jax.tree_util.tree_flatten_with_path(trajectory)[0], jax.tree.leaves(expected)):
        if jnp.shape(leaf) != batch + want.shape:
            raise ValueError(f"{label}{jax.tree_util.keystr(path)} has shape {jnp.shape(leaf)}; the task needs "
                             f"{batch + want.shape}" + (f" = (B,) + {want.shape}" if batch else ""))
        if not isinstance(leaf, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(leaf))):
            bad = np.unique(np.nonzero(~np.isfinite(np.asarray(leaf)))[0]).tolist() if batch else []
            raise ValueError(f"{label}{jax.tree_util.keystr(path)} has non-finite entries (NaN or inf)"
                             + (f" in instances {bad}" if batch else ""))


def _check_guesses(guesses, expected, size=None):
    """guesses: a batched Trajectory whose instances have the shapes of ``expected`` (one
    instance's ShapeDtypeStructs); size: the batch size it must have (None: any)."""
    if not isinstance(guesses, Trajectory):
        raise TypeError(f"guesses must be a batched Trajectory or a list of Trajectories, got {type(guesses).__name__}")
    if jnp.ndim(guesses.total_time) != 1:
        raise ValueError(f"guesses must have a leading batch axis (total_time of shape (B,)), got total_time of shape "
                         f"{jnp.shape(guesses.total_time)}; solve one guess with solve.solve_task, or stack "
                         "guesses with stack_trajectories")
    count = jnp.shape(guesses.total_time)[0]
    _check_shapes(guesses, expected, (count,), "guesses")
    if size is not None and count != size:
        raise ValueError(f"{count} guesses for a batch of {size} tasks: give one guess per task")


# ------------------------------------------------------------------------------------- solve

@jax.jit
def published_guesses(tasks):
    """The published initial guess (``tasks.initial_guess``) of every task of a batched ``Task``:
    a batched ``Trajectory``."""
    return jax.vmap(initial_guess)(tasks)


def batch_mesh(devices=None):
    """A one-axis ``jax.sharding.Mesh`` named "batch" over ``devices`` (default: every device
    ``jax.devices()`` sees: on several hosts, after ``jax.distributed.initialize()``, those of
    all the hosts), for the ``mesh`` argument of ``solve_batch``."""
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("a batch mesh needs at least one device")
    return jax.sharding.Mesh(np.asarray(devices), ("batch",))


def _vectorised_on(mesh):
    """Whether each device of ``mesh`` vmaps its instances: not on CPU devices. Several CPU
    devices of one process share one thread pool, and XLA's batched LAPACK kernels (Cholesky)
    wait in it for work they queue to it: with every pool thread running a device's program they
    wait forever (seen on 2 simulated CPU devices: the sharded robot batch hung with 2 instances
    per device, never with 1). Unbatched kernels queue nothing."""
    return mesh.devices.flat[0].platform != "cpu"


@dataclasses.dataclass(frozen=True)
class BatchProgress:
    """Where a batch stands, passed to ``solve_batch``'s ``progress`` as each instance ends:
    ``index`` and ``status`` of the instance that just ended; counts of instances ``finished``,
    ``running`` and ``queued``; ``best`` objective among the converged ones (NaN before the
    first); ``schedules``, how many distinct contact schedules the converged ones show."""

    index: int
    status: ip.Status
    finished: int
    running: int
    queued: int
    best: float
    schedules: int

    def __str__(self):
        best = "none converged" if np.isnan(self.best) else f"best objective {self.best:.6g}"
        return (f"{self.finished} finished, {self.running} running, {self.queued} queued; {best}; "
                f"{self.schedules} contact schedule{'s' if self.schedules != 1 else ''}")


class _Tally:
    """``on_finish`` for ``schedule``: counts the ended instances and calls ``progress``."""

    def __init__(self, size, parallel, progress):
        self.size, self.parallel, self.progress = size, parallel, progress
        self.finished, self.best, self.schedules = 0, np.nan, set()

    def __call__(self, index, result):
        self.finished += 1
        status = result.status
        if status == ip.Status.CONVERGED:
            objective = float(result.solution.objective)
            self.best = objective if np.isnan(self.best) else min(self.best, objective)
            self.schedules.add(analysis.airborne_corners(result.trajectory).tobytes())
        if self.progress is not None:
            running = min(self.parallel, self.size - self.finished)
            self.progress(BatchProgress(index, status, self.finished, running, self.size - self.finished - running,
                                        self.best, len(self.schedules)))


DEFAULT_SLOTS = 64


def _run(tasks, guesses, options, mesh, strategy, slots, progress, time_budget, interruptible):
    """The batch solve: split over ``mesh``'s devices when given, else by ``strategy``
    (``schedule``)."""
    stopping.check_budget(time_budget)
    size = batch_size(guesses)
    if mesh is not None:
        if not isinstance(mesh, jax.sharding.Mesh) or mesh.axis_names != ("batch",):
            raise TypeError(f"mesh must be a one-axis Mesh named 'batch' (see batch_mesh), got {mesh!r}")
        if time_budget is not None or interruptible or strategy is not None or progress is not None:
            raise ValueError("a sharded batch is one call: it takes no strategy, progress, time_budget or interrupt")
        if size % mesh.devices.size:
            raise ValueError(f"a batch of {size} does not split evenly over {mesh.devices.size} devices: give a "
                             f"multiple of {mesh.devices.size} instances (repeat a guess to pad)")
        split = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("batch"))
        return programs.sharded_batch_solve(jax.device_put(tasks, split), jax.device_put(guesses, split), options, mesh,
                                            _vectorised_on(mesh))
    strategy = schedule.default_strategy(strategy, size)
    slots = DEFAULT_SLOTS if slots is None else slots
    if isinstance(slots, bool) or not isinstance(slots, (int, np.integer)) or slots < 1:
        raise ValueError(f"slots must be a positive integer, got {slots!r}")
    if strategy == "queue":
        results = schedule.run_queue(tasks, guesses, options, _Tally(size, 1, progress), time_budget, interruptible)
    elif strategy == "processes":
        if time_budget is not None or interruptible:
            raise ValueError("strategy 'processes' takes no time_budget or interrupt: use 'queue' or 'slots'")
        workers = min(len(schedule.cores()), size)
        results = schedule.run_processes(tasks, guesses, options, _Tally(size, workers, progress), workers)
    else:
        tally = _Tally(size, min(slots, size), progress)
        results = schedule.run_slots(tasks, guesses, options, slots, tally, time_budget, interruptible)
    return jax.tree.map(_stack_leaves, *results)


def solve_batch(tasks, guesses=None, options=programs.DEFAULT_OPTIONS, mesh=None, strategy=None, *, slots=None,
                progress=None, time_budget=None, interruptible=False):
    """Solve many instances: one task from B initial guesses (multi-start), or B tasks of one
    structure, instance i of ``tasks`` from guess i. No instance's answer depends on the others.

    tasks: one ``Task`` (broadcast to the batch: multi-start), a batched ``Task``
    (``stack_tasks``) or a list of B ``Task``s (stacked here), whose targets, heights, weights and
    bounds may differ. guesses: a batched ``Trajectory`` (leaves (B, N + 1, ...), total time
    (B,)), e.g. from ``sample_guesses``, or a list of B ``Trajectory``s; default, for batched
    tasks, the published initial guess of each. options: ``ip.Options`` (static).
    Returns a batched ``TaskSolution`` (every leaf (B, ...)): see ``instance`` and ``summarise``.

    strategy (``jaxmm.schedule``): "queue", one instance after another through the compiled
    single solve (``solve_task``'s own programs: nothing more to compile, each instance costs its
    own iterations and equals its ``solve_task`` bit for bit); "processes", the same spread over
    one worker process per core, each pinned to its core (every worker compiles the solve once,
    all at the same time; no time budget or interrupt); "slots", ``slots`` instances
    (default ``DEFAULT_SLOTS``) advancing together in one vmapped solve, each slot taking the next
    guess as soon as its instance stops (what accelerators are for: a batch costs about its total
    iterations divided by the slots; on a CPU each batched iteration costs the sum of its slots'
    iterations). Default (None): "slots" on an accelerator; on a CPU "processes" for more than one
    instance and core, else "queue".
    progress: called on the host with a ``BatchProgress`` as each instance ends.
    time_budget [s], interruptible: as for ``solve.solve_task``, for the whole batch: the
    instances running or queued when it stops get status ``TIME_LIMIT`` or ``INTERRUPTED`` (a
    queued one keeps its guess), the others keep theirs.

    mesh: a ``batch_mesh`` to split the instances over several devices (B a multiple of their
    number) in one call: each device runs its instances one after another on CPU devices,
    vmapped on accelerators; with no strategy, progress, budget or interrupt.
    """
    if isinstance(tasks, Sequence):
        tasks = stack_tasks(tasks)
    if not isinstance(tasks, Task):
        raise TypeError(f"tasks must be a Task, a batched Task or a list of Tasks, got {type(tasks).__name__}")
    if jnp.ndim(tasks.params.min_dt) == 0:  # one task, many guesses
        if guesses is None:
            raise ValueError("a batch of one task needs its guesses (see sample_guesses)")
        guesses = _batched_guesses(guesses)
        _check_guesses(guesses, jax.eval_shape(initial_guess, tasks))
        tasks = broadcast_task(tasks, batch_size(guesses))
    else:
        size = batch_size(tasks)
        guesses = _batched_guesses(published_guesses(tasks) if guesses is None else guesses)
        _check_guesses(guesses, jax.eval_shape(initial_guess, instance(tasks, 0)), size)
    return _run(tasks, guesses, options, mesh, strategy, slots, progress, time_budget, interruptible)


# ---------------------------------------------------------------------------------- guesses


def _is_key(key):
    dtype = getattr(key, "dtype", None)
    if dtype is None:
        return False
    if jnp.issubdtype(dtype, jax.dtypes.prng_key):
        return jnp.ndim(key) == 0
    return dtype == jnp.uint32 and jnp.shape(key) == (2,)


def sample_guesses(task, key, n, *, around=None, joint_scale=0.1, horizon_scale=1.0, contact_shift=0.05,
                   contact_lift=0.05, thrust_scale=30.0):
    """n initial guesses perturbed at random around ``around`` (default: the published guess),
    as one batched ``Trajectory`` (leaves (n, N + 1, ...), total time (n,)) for ``solve_batch``.

    key: a JAX PRNG key (``jax.random.key(seed)``); the same key gives the same guesses.
    Per guess, with α_k = k / N the ramp from knot 0 to knot N:

    * posture: every joint shifted by δ ~ N(0, joint_scale²) [rad], the same shift at every knot;
    * horizon: T_total = (1 − horizon_scale) T̄ + horizon_scale U(N min_dt, N max_dt) [s]
      (horizon_scale in [0, 1]; 1: uniform over the whole box);
    * contact points: the corners of each rigid body (each sole) shifted horizontally together by
      δ ~ N(0, contact_shift²) per axis [m] and lifted by α_k h, h ~ U(0, contact_lift) [m]
      (a foot that rises towards the end; knot 0 stays on the ground);
    * thrust: each jet's profile plus α_k δ, δ ~ N(0, thrust_scale²) [N].

    Every other variable is that of ``around``. The result is clipped into the variable boxes
    (``constraints.variable_bounds``: joint limits, thrust range, T_total range, the fixed
    boundary values), so it is inside them; the solver's bound push then moves it strictly
    inside. A scale of 0 leaves its variables unperturbed.
    """
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive integer number of guesses, got {n!r}")
    if not _is_key(key):
        raise TypeError(f"key must be one JAX PRNG key (jax.random.key(seed)), got {key!r}")
    for name, value in (("joint_scale", joint_scale), ("contact_shift", contact_shift),
                        ("contact_lift", contact_lift), ("thrust_scale", thrust_scale)):
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be finite and non-negative, got {value!r}")
    if not 0 <= horizon_scale <= 1:
        raise ValueError(f"horizon_scale must be in [0, 1], got {horizon_scale!r}")
    base = initial_guess(task) if around is None else around
    if not isinstance(base, Trajectory):
        raise TypeError(f"around must be a Trajectory, got {type(base).__name__}")
    _check_shapes(base, jax.eval_shape(initial_guess, task), (), "around")
    scales = (joint_scale, horizon_scale, contact_shift, contact_lift, thrust_scale)
    return _sample(task, base, jax.random.split(key, n), *(jnp.asarray(x, dtype=float) for x in scales))


@jax.jit
def _sample(task, base, keys, joint_scale, horizon_scale, contact_shift, contact_lift, thrust_scale):
    """``sample_guesses`` for keys (n,), compiled once per task structure and n."""
    lower, upper = variable_bounds(task)
    layout = task.layout
    topology = task.robot.model.topology
    bodies = [topology.frame_body[topology.frame_names.index(f)] for f in task.robot.contact_frames]
    # Corner c belongs to rigid body groups[c]: the corners of one sole move together.
    groups = np.unique(np.asarray(bodies, dtype=int), return_inverse=True)[1].reshape(-1)
    n_groups = int(groups.max(initial=-1)) + 1
    ramp = jnp.linspace(0.0, 1.0, task.n_knots)[:, None]  # (N + 1, 1) α_k

    def one(key):
        k_joint, k_time, k_shift, k_lift, k_thrust = jax.random.split(key, 5)
        knots = base.knots
        posture = joint_scale * jax.random.normal(k_joint, (layout.n_joints,))
        shift = contact_shift * jax.random.normal(k_shift, (n_groups, 2))[groups]  # (nc, 2)
        lift = contact_lift * jax.random.uniform(k_lift, (n_groups,))[groups]  # (nc,)
        offset = jnp.concatenate([jnp.broadcast_to(shift, (task.n_knots, layout.n_contacts, 2)),
                                  (ramp * lift)[..., None]], axis=-1)
        thrust = thrust_scale * jax.random.normal(k_thrust, (layout.n_jets,))
        horizon = jax.random.uniform(k_time, minval=lower.total_time, maxval=upper.total_time)
        guess = Trajectory(
            dataclasses.replace(
                knots,
                joint_positions=knots.joint_positions + posture,
                contact_points=knots.contact_points + offset,
                thrust=knots.thrust + ramp * thrust,
            ),
            (1.0 - horizon_scale) * base.total_time + horizon_scale * horizon,
        )
        return jax.tree.map(jnp.clip, guess, lower, upper)

    return jax.vmap(one)(keys)


# ---------------------------------------------------------------------------------- summary


@dataclasses.dataclass(frozen=True)
class InstanceResult:
    """One instance of a batch: its index, why it stopped, objective, max violation (the NLP's
    units, boxes included), Newton iterations and the index of its contact schedule in
    ``BatchSummary.schedules``."""

    index: int
    status: ip.Status
    objective: float
    violation: float
    iterations: int
    schedule: int


@dataclasses.dataclass(frozen=True)
class ContactSchedule:
    """A contact schedule shared by some instances: ``airborne`` (N + 1, nc) bool (corner off
    the ground at a knot, ``analysis.airborne_corners``), the ``flight_knots`` (every corner off
    the ground) and the ``members`` (instance indices, best first)."""

    airborne: np.ndarray
    flight_knots: tuple
    members: tuple


@dataclasses.dataclass(frozen=True)
class BatchSummary:
    """The instances of a batch ranked best first (``ranking``) and their distinct contact
    schedules (``schedules``, in the order of their best member). ``corners``: the contact
    frame names; ``tolerance``: the violation below which an instance counts as feasible."""

    ranking: tuple
    schedules: tuple
    corners: tuple
    tolerance: float

    @property
    def best(self):
        """The best instance (an ``InstanceResult``)."""
        return self.ranking[0]

    def __str__(self):
        converged = sum(r.status is ip.Status.CONVERGED for r in self.ranking)
        feasible = sum(_tier(r, self.tolerance) == 1 for r in self.ranking)
        lines = [
            f"{len(self.ranking)} instances: {converged} converged, {feasible} feasible (violation ≤ "
            f"{self.tolerance:g}) without converging, {len(self.ranking) - converged - feasible} neither; "
            f"{len(self.schedules)} contact schedule{'s' if len(self.schedules) != 1 else ''}",
            "",
            f"{'rank':>4}  {'instance':>8}  {'status':<14}  {'objective':>12}  {'violation':>9}  {'iterations':>10}  schedule",
        ]
        for rank, r in enumerate(self.ranking, start=1):
            lines.append(f"{rank:>4}  {r.index:>8}  {r.status.name.lower():<14}  {r.objective:>12.6g}  "
                         f"{r.violation:>9.2g}  {r.iterations:>10}  {r.schedule + 1}")
        width = max((len(c) for c in self.corners), default=0)
        for number, group in enumerate(self.schedules, start=1):
            lines += ["", f"schedule {number}: instances {', '.join(map(str, group.members))}; "
                          f"flight knots {_ranges(group.flight_knots)}"]
            if self.corners:
                n_knots = group.airborne.shape[0]
                lines.append(f"  {'knot':<{width}}  " + "".join(str(k % 10) for k in range(n_knots)))
                for name, column in zip(self.corners, group.airborne.T):
                    lines.append(f"  {name:<{width}}  " + "".join("." if up else "#" for up in column))
        lines += ["", "(# on the ground, . off it)"] if self.corners else []
        return "\n".join(lines)


def _ranges(knots):
    """(3, 4, 5, 9) → "3–5, 9"; () → "none"."""
    if not knots:
        return "none"
    spans = [[knots[0], knots[0]]]
    for k in knots[1:]:
        if k == spans[-1][1] + 1:
            spans[-1][1] = k
        else:
            spans.append([k, k])
    return ", ".join(f"{a}–{b}" if b > a else str(a) for a, b in spans)


def _tier(result, tolerance):
    """0: converged; 1: feasible (violation ≤ tolerance, finite numbers) without converging;
    2: neither."""
    if result.status is ip.Status.CONVERGED:
        return 0
    if result.status is not ip.Status.NAN and result.violation <= tolerance and np.isfinite(result.objective):
        return 1
    return 2


def _rank_key(result, tolerance):
    """Converged, then feasible, then the rest; the first two by objective, the rest by
    violation then objective (non-finite numbers last)."""
    finite = lambda x: x if np.isfinite(x) else np.inf  # noqa: E731
    tier = _tier(result, tolerance)
    if tier < 2:
        return (tier, finite(result.objective), 0.0)
    return (tier, finite(result.violation), finite(result.objective))


def summarise(task, batch_solution, *, tolerance=programs.DEFAULT_OPTIONS.tolerance, contact_height=0.01):
    """Rank the instances of a batched ``TaskSolution`` and group them by contact schedule.

    Ranking: converged instances first, then those feasible to ``tolerance`` (the solver's
    violation, NLP units) that did not converge, each by objective; then the rest by violation.
    A schedule is which contact corners are off the ground (higher than contact_height [m], as
    in ``analysis.validate``) at which knots. task: the task (or the batched task) solved; only
    its contact frame names are read. Returns a ``BatchSummary``; ``print`` it for a table.
    """
    batch_size(batch_solution)  # rejects a solution that is not batched, naming a scalar leaf
    solution = batch_solution.solution
    status, objective, violation, iterations = (
        np.asarray(x) for x in (solution.status, solution.objective, solution.violation, solution.iterations))
    every = analysis.airborne_corners(batch_solution.trajectory, contact_height)  # (B, N + 1, nc)
    keys, schedules, results = {}, [], []
    for i, airborne in enumerate(every):
        key = airborne.tobytes()
        if key not in keys:
            keys[key] = len(schedules)
            schedules.append(airborne)
        results.append(InstanceResult(index=i, status=ip.Status(int(status[i])), objective=float(objective[i]),
                                      violation=float(violation[i]), iterations=int(iterations[i]),
                                      schedule=keys[key]))
    ranking = sorted(results, key=lambda r: _rank_key(r, tolerance))
    # Schedules numbered in the order of their best member.
    order = list(dict.fromkeys(r.schedule for r in ranking))
    renumber = {old: new for new, old in enumerate(order)}
    ranking = tuple(dataclasses.replace(r, schedule=renumber[r.schedule]) for r in ranking)
    grouped = tuple(
        ContactSchedule(airborne=schedules[old], flight_knots=analysis.flight_knots(schedules[old]),
                        members=tuple(r.index for r in ranking if r.schedule == new))
        for new, old in enumerate(order)
    )
    return BatchSummary(ranking=ranking, schedules=grouped, corners=tuple(task.robot.contact_frames),
                        tolerance=float(tolerance))
