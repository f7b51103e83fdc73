"""How a batch's instances are run: the three strategies of ``batch.solve_batch``.

``queue``: the instances one after another through the compiled programs of a single solve
(``programs.compiled_programs``: the ones ``solve_task`` compiles and reuses), so that the batch
compiles nothing beyond one solve, each instance costs exactly its own iterations, and its answer
is bit for bit that of ``solve_task``. On a CPU this is the fastest way to run many solves in one
process: XLA already spreads one solve's kernels over the cores, and neither two threads nor two
CPU devices running two solves at once finished sooner (docs/design-decisions.md, "CPU batches:
one solve after another").

``processes``: the instances spread over worker processes, one per core, each pinned to its core
and taking the next instance of the queue when it finishes one, through its own compiled single
solve (all workers compile at once, in the time of one compile). A solve's small kernels run
faster on one core than spread over two, so this is what uses a CPU's cores for a batch.

``slots``: ``slots`` instances advance together in one vmapped ``advance`` (what accelerators
are for), ``SLICE_ITERATIONS`` iterations at a time; between slices, an instance that has stopped
(converged, failed, or at its iteration cap) is finished and its slot takes the next guess of
the queue (iteration-level batching), so that a batch costs about its total iterations divided
by the slots, not the slots times the slowest instance. Each slot keeps its own iteration count,
cap and status: an instance's iterates are those of its single solve, up to the rounding of
batched kernels.

All call ``on_finish(index, result)`` on the host as each instance ends. The queue and the slots
stop every instance still running or queued when a time budget runs out
(``Status.TIME_LIMIT``) or at a Ctrl-C (``Status.INTERRUPTED``) when asked to; an instance that
never started keeps its guess.
"""

import contextlib
import functools
import math
import multiprocessing
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm import compilation, programs
from jaxmm.solver import interior_point as ip
from jaxmm.solver import stopping

# Iterations between two refills of the slots: an instance that stops waits at most this many
# iterations for its slot to be refilled, and each slice costs one transfer of the statuses.
SLICE_ITERATIONS = 10

STRATEGIES = ("queue", "processes", "slots")


def cores():
    """The CPU cores this process may run on."""
    return sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else list(range(os.cpu_count() or 1))


def default_strategy(strategy, size, devices=None):
    """``strategy`` when given; else, for a batch of ``size``, "slots" on accelerators and, on a
    CPU, "processes" when there are more instances than one and more cores than one, "queue"
    otherwise."""
    if strategy is not None:
        if strategy not in STRATEGIES:
            raise ValueError(f"strategy must be one of {STRATEGIES} (or None: chosen per backend), got {strategy!r}")
        return strategy
    devices = jax.devices() if devices is None else devices
    if devices[0].platform != "cpu":
        return "slots"
    return "processes" if size > 1 and len(cores()) > 1 else "queue"


@jax.jit
def _take(tree, i):
    """Instance i (traced: one compilation for every index) of a batched pytree."""
    return jax.tree.map(lambda leaf: leaf[i], tree)


@functools.partial(jax.jit, donate_argnums=0)
def _put(tree, i, item):
    """The batched pytree ``tree`` with instance i replaced by ``item``."""
    return jax.tree.map(lambda leaf, new: leaf.at[i].set(new), tree, item)


@jax.jit
def _stack(items):
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *items)


class _Clock:
    """The batch's stopping rule: a deadline ``time_budget`` [s] after ``begin()`` and a Ctrl-C
    flag (``stopping.interrupt_flag``); ``stopped()`` → the status that ends the batch, or None."""

    def __init__(self, time_budget, flag):
        self.time_budget, self.flag, self.deadline = time_budget, flag, math.inf

    def begin(self):
        if self.time_budget is not None:
            self.deadline = time.monotonic() + self.time_budget

    def left(self):
        return None if self.time_budget is None else self.deadline - time.monotonic()

    def stopped(self):
        if self.flag["set"]:
            return int(ip.Status.INTERRUPTED)
        if time.monotonic() >= self.deadline:
            return int(ip.Status.TIME_LIMIT)
        return None


def run_queue(tasks, guesses, options, on_finish, time_budget=None, interruptible=False):
    """The batch's instances one after another through one single solve's compiled programs.
    tasks, guesses: batched (B leading); returns the B ``TaskSolution``s in order."""
    size = np.shape(guesses.total_time)[0]
    first = _take(tasks, 0)
    started, advanced, finished = programs.compiled_programs(first, _take(guesses, 0), options, None, None)
    iterating = ip.iteration_options(options)
    sliced = time_budget is not None or interruptible
    results = []
    with stopping.interrupt_flag(interruptible) as flag:
        clock = _Clock(time_budget, flag)
        clock.begin()
        for j in range(size):
            task = _take(tasks, j)
            state = started(task, _take(guesses, j), options, None, None)
            advance = lambda s, until, task=task: advanced(task, s, iterating, until)  # noqa: E731
            finish = lambda s, stopped, task=task: finished(task, s, stopped)  # noqa: E731
            results.append(_run_one(state, advance, finish, iterating.max_iterations, clock if sliced else None))
            on_finish(j, results[-1])
    return results


def _run_one(state, advance, finish, max_iterations, clock):
    """One started instance to its end: one call without a ``clock``, else in slices that stop
    at the clock's deadline or Ctrl-C (``stopping.run``)."""
    if clock is None:
        return finish(advance(state, max_iterations), int(ip.Status.MAX_ITERATIONS))
    stop, left = clock.stopped(), clock.left()
    if stop is None and left is not None and left <= 0:
        stop = int(ip.Status.TIME_LIMIT)
    if stop is not None:
        return finish(state, stop)
    return stopping.run(state, advance, finish, max_iterations, time_budget=left, flag=clock.flag)


_WORKER = {}  # in a worker process of ``run_processes``: its batch and solve


def _worker_start(tasks, guesses, options, places, cache, counter):
    """A worker process of ``run_processes``: pinned to the next core of ``places``, with the
    parent's executable store (``cache``: its directory, or None)."""
    with counter.get_lock():
        number = counter.value
        counter.value += 1
    if hasattr(os, "sched_setaffinity"):  # Linux; elsewhere the system places the workers
        os.sched_setaffinity(0, {places[number % len(places)]})
    if cache is not None:
        compilation.use_persistent_cache(cache)
    _WORKER.update(tasks=tasks, guesses=guesses, options=options)


def _worker_solve(j):
    """(j, instance j's ``TaskSolution`` with NumPy leaves), solved in this worker by the single
    solve (``programs.compile_solve``: compiled at the first instance, reused after)."""
    tasks, guesses, options = _WORKER["tasks"], _WORKER["guesses"], _WORKER["options"]
    return j, jax.device_get(programs.compile_solve(_take(tasks, j), _take(guesses, j), options)())


@contextlib.contextmanager
def _main_script_hidden():
    """While starting workers: ``__main__`` without its file and spec, so that ``spawn`` does not
    re-run the caller's script in every worker (a script without an ``if __name__ ==
    "__main__"`` guard would start workers recursively); the workers need only jaxmm."""
    main = sys.modules.get("__main__")
    if main is None:
        yield
        return
    saved = {key: main.__dict__.pop(key) for key in ("__file__",) if key in main.__dict__}
    spec, main.__spec__ = getattr(main, "__spec__", None), None
    try:
        yield
    finally:
        main.__dict__.update(saved)
        main.__spec__ = spec


def run_processes(tasks, guesses, options, on_finish, workers=None):
    """The batch's instances spread over ``workers`` processes (default: one per core this
    process may use), each pinned to its own core and solving the next instance of the queue
    as it finishes one, through its own compiled single solve (compiled in every worker at
    once, or loaded from the executable store where the parent has one). Returns the B
    ``TaskSolution``s (NumPy leaves) in order."""
    size = np.shape(guesses.total_time)[0]
    places = cores()
    workers = min(len(places) if workers is None else workers, size)
    cache = jax.config.jax_compilation_cache_dir if compilation.store() is not None else None
    context = multiprocessing.get_context("spawn")  # a fork would copy JAX's threads' locks
    counter = context.Value("i", 0)
    arguments = (jax.device_get(tasks), jax.device_get(guesses), options, places, cache, counter)
    results = [None] * size
    with _main_script_hidden():
        pool = context.Pool(workers, initializer=_worker_start, initargs=arguments)
    with pool:
        for j, result in pool.imap_unordered(_worker_solve, range(size)):
            results[j] = result
            on_finish(j, result)
    return results


def _call(program, *args):
    """``program`` (a ``compilation.jit``) on ``args`` through its compiled ``Program``: the
    executable a single solve (``programs.compiled_programs``) runs, not a second compilation."""
    return program.compiled(*args)(*args)


@functools.partial(jax.jit, static_argnames="options")
def slots_advance(tasks, states, options, until):
    """Every slot's ``state`` iterated until it stops or reaches its own ``until`` (S,)."""
    return jax.vmap(lambda task, state, last: programs.advance(task, state, options, last))(tasks, states, until)


def run_slots(tasks, guesses, options, slots, on_finish, time_budget=None, interruptible=False):
    """The batch's instances in ``slots`` vmapped slots, each refilled from the queue as its
    instance stops. tasks, guesses: batched (B leading); returns the B ``TaskSolution``s."""
    size = np.shape(guesses.total_time)[0]
    slots = min(slots, size)
    iterating = ip.iteration_options(options)
    cap = iterating.max_iterations

    def begin(j):
        return _call(programs.start, _take(tasks, j), _take(guesses, j), options, None, None)

    owner = list(range(slots))  # the instance in each slot; None once the queue is empty
    following = slots
    states = _stack([begin(j) for j in owner])
    slot_tasks = _stack([_take(tasks, j) for j in owner])
    results = [None] * size
    with stopping.interrupt_flag(interruptible) as flag:
        clock = _Clock(time_budget, flag)
        while any(j is not None for j in owner):
            done = np.asarray(states.iterations)
            active = np.array([j is not None for j in owner])
            until = np.where(active, np.minimum(done + SLICE_ITERATIONS, cap), done).astype(done.dtype)
            states = slots_advance(slot_tasks, states, iterating, jnp.asarray(until))
            iterations, status = np.asarray(states.iterations), np.asarray(states.status)
            if clock.deadline == math.inf:  # the budget counts from the end of the first slice (compiling)
                clock.begin()
            stop = clock.stopped()
            for s, j in enumerate(owner):
                if j is None or (stop is None and status[s] == int(ip.Status.RUNNING) and iterations[s] < cap):
                    continue
                ending = int(ip.Status.MAX_ITERATIONS) if stop is None else stop
                results[j] = _call(programs.finish, _take(slot_tasks, s), _take(states, s), ending)
                on_finish(j, results[j])
                owner[s] = None
                if stop is None and following < size:
                    owner[s] = following
                    states = _put(states, s, begin(following))
                    slot_tasks = _put(slot_tasks, s, _take(tasks, following))
                    following += 1
            if stop is not None:
                for j in range(following, size):  # never started: their guesses
                    results[j] = _call(programs.finish, _take(tasks, j), begin(j), stop)
                    on_finish(j, results[j])
                break
    return results
