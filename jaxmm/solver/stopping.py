"""Solves that can be stopped early: a time budget or Ctrl-C ends them between iterations with the
last iterate and a status that says why (``Status.TIME_LIMIT``, ``Status.INTERRUPTED``).

A compiled solve is one XLA call: nothing on the host can stop it halfway, and a Ctrl-C waits
for its end. So the solve runs in slices (``interior_point.advance`` up to a given iteration
count, one compilation for every count) and the host decides between slices whether to go on.
The first slice is one iteration (it may include compiling); the next are sized to take about
``SLICE_SECONDS`` each, from the time the last one took, and never to run past the time left:
a budget is overshot by about one iteration. An interrupt is caught as a flag (the first Ctrl-C)
and acted on when the running slice ends; a second Ctrl-C raises ``KeyboardInterrupt`` at once.

Works the same for one solve and for a vmapped batch of them (status and iterations (B,)):
the batch goes on while any instance runs, and the instances still running when it stops get
the stopping status; the others keep theirs.
"""

import contextlib
import math
import numbers
import signal
import threading
import time

import numpy as np

from jaxmm.solver.interior_point import Status

SLICE_SECONDS = 0.5  # host check interval while iterating
MAX_SLICE = 1000  # iterations


@contextlib.contextmanager
def interrupt_flag(enabled):
    """A dict whose "set" becomes True at the first SIGINT while inside (only on the main
    thread, where Python delivers signals; elsewhere the flag never sets)."""
    flag = {"set": False}
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, frame):
        if flag["set"]:
            raise KeyboardInterrupt
        flag["set"] = True

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, previous)


def check_budget(time_budget):
    """Raise ValueError unless ``time_budget`` is None or a positive, finite number of seconds."""
    if time_budget is not None and (isinstance(time_budget, bool) or not isinstance(time_budget, numbers.Real)
                                    or not 0 < time_budget < math.inf):
        raise ValueError(f"time_budget must be a positive number of seconds, got {time_budget!r}")


def run(state, advance, finish, max_iterations, *, time_budget=None, interruptible=True, flag=None):
    """Iterate ``state`` (an ``interior_point.State``, possibly batched) to the end, in slices.

    advance(state, until) → state: iterations up to ``until`` (an int); finish(state, stopped) →
    the result, with ``stopped`` the status of instances still running (a ``Status`` int).
    time_budget: seconds of iterating after the first slice of one iteration (None: no limit;
    the first slice may include compiling: it does not count); interruptible: the first Ctrl-C
    stops the solve after the running slice; flag: the dict of an enclosing ``interrupt_flag``
    to watch instead of installing one (a batch of solves stopped by one Ctrl-C). Returns finish's result: ``MAX_ITERATIONS`` if the
    iteration limit ended it, else ``TIME_LIMIT`` or ``INTERRUPTED`` for whatever still ran.
    """
    check_budget(time_budget)
    deadline = math.inf
    stopped, size, per_iteration = Status.MAX_ITERATIONS, 1, None
    with contextlib.nullcontext(flag) if flag is not None else interrupt_flag(interruptible) as interrupt:
        while True:
            done = np.asarray(state.iterations).max(initial=0)
            left = deadline - time.monotonic()
            if per_iteration is not None:
                size = int(np.clip(min(SLICE_SECONDS, left) / per_iteration, 1, MAX_SLICE))
            began = time.monotonic()
            state = advance(state, int(done) + size)
            iterations = np.asarray(state.iterations)  # the host waits for the slice here
            running = (np.asarray(state.status) == int(Status.RUNNING)) & (iterations < max_iterations)
            taken = iterations.max(initial=0) - done
            if taken > 0:
                per_iteration = max((time.monotonic() - began) / taken, 1e-6)
            if time_budget is not None and deadline == math.inf:
                deadline = time.monotonic() + time_budget
            if not running.any():
                break
            if interrupt["set"]:
                stopped = Status.INTERRUPTED
                break
            if time.monotonic() >= deadline:
                stopped = Status.TIME_LIMIT
                break
    return finish(state, int(stopped))
