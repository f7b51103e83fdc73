"""Solves stopped early (``jaxmm.solver.stopping``): in slices they are the one-call solve; a time
budget or a Ctrl-C stops them between iterations with the last iterate and a status that says
why; a batch stops together, its finished instances keeping their own status."""

import signal
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmm  # noqa: F401  (float64)
from jaxmm.solver import interior_point as ip
from jaxmm.solver import stopping
from jaxmm.stagewise import StagewiseFunctions, StagewiseNLP

K = 10
EMPTY = jnp.zeros(0)


# A double integrator pushed to x = a at the last knot by a capped control u² ≤ 0.05 (a nonlinear
# inequality): a few dozen interior-point iterations.
def _knot_cost(a, z, theta, d):
    return 0.5 * (z[1] ** 2 + z[2] ** 2) + d * 50.0 * (z[0] - a) ** 2


def _global_cost(a, theta):
    return 0.5 * theta[0] ** 2


def _dynamics(a, z, z_next, theta):
    return jnp.array([z_next[0] - z[0] - 0.1 * z[1], z_next[1] - z[1] - 0.1 * z[2]])


def _energy(a, z, theta):
    return z[2:3] ** 2


def _none(a, z, z_next, theta):
    return EMPTY


FUNCTIONS = StagewiseFunctions(_knot_cost, _global_cost, lambda a, z, t: EMPTY, _dynamics, _energy, _none)


def _problem(a=1.0):
    lower = jnp.full((K, 3), -jnp.inf).at[0, :2].set(0.0)
    upper = jnp.full((K, 3), jnp.inf).at[0, :2].set(0.0)
    return StagewiseNLP(
        args=jnp.asarray(a), knot_data=jnp.zeros(K).at[-1].set(1.0), z_lower=lower, z_upper=upper,
        theta_lower=jnp.full(1, -jnp.inf), theta_upper=jnp.full(1, jnp.inf),
        path_lower=jnp.array([-jnp.inf]), path_upper=jnp.array([0.05]), transition_lower=EMPTY,
        transition_upper=EMPTY, functions=FUNCTIONS,
    )


OPTIONS = ip.Options(tolerance=1e-9, stationarity=1e-8, max_iterations=200)
Z0, THETA0 = jnp.zeros((K, 3)), jnp.zeros(1)
solve = jax.jit(ip.solve, static_argnames="options")
start = jax.jit(ip.start, static_argnames="options")
advance = jax.jit(ip.advance, static_argnames="options")
finish = jax.jit(ip.finish)


def _run(nlp, advance_hook=None, **kwargs):
    """stopping.run on nlp from (Z0, θ0); advance_hook(slice number) runs after each slice."""
    slices = []

    def step(state, until):
        state = advance(nlp, state, OPTIONS, until)
        slices.append(int(np.max(state.iterations)))
        if advance_hook is not None:
            advance_hook(len(slices))
        return state

    result = stopping.run(start(nlp, Z0, THETA0, OPTIONS), step, lambda s, stopped: finish(nlp, s, stopped),
                          OPTIONS.max_iterations, **kwargs)
    return result, slices


@pytest.fixture(scope="module")
def whole():
    solution = solve(_problem(), Z0, THETA0, OPTIONS)
    assert ip.Status(int(solution.status)) is ip.Status.CONVERGED and int(solution.iterations) > 10
    return solution


def _stopped_at(iterations):
    """The one-call solve limited to ``iterations``: the iterate a stop after them must return."""
    limited = ip.Options(**{**OPTIONS.__dict__, "max_iterations": iterations})
    return solve(_problem(), Z0, THETA0, limited)


def test_a_solve_in_slices_is_the_one_call_solve(whole, monkeypatch):
    monkeypatch.setattr(stopping, "SLICE_SECONDS", 1e-9)  # slices of one iteration
    sliced, slices = _run(_problem(), interruptible=False)
    assert ip.Status(int(sliced.status)) is ip.Status.CONVERGED
    assert int(sliced.iterations) == int(whole.iterations) == len(slices)
    np.testing.assert_allclose(np.asarray(sliced.Z), np.asarray(whole.Z), rtol=0, atol=1e-12)
    # The slices and the one call are two compiled programs whose fusions round differently: the
    # history's violations and stationarities agree to rounding of their own size, not bit for bit.
    np.testing.assert_allclose(np.asarray(sliced.history), np.asarray(whole.history), rtol=1e-8, atol=1e-12,
                               equal_nan=True)


def test_the_iterations_ignore_the_settings_only_the_start_reads():
    """``iteration_options`` resets barrier0, bound_push and max_gradient, so that one compiled
    ``advance`` serves cold and warm starts: from the same state, advancing with the settings
    changed or reset must give the same iterate (it would not if ``advance`` read them)."""
    changed = ip.Options(**{**OPTIONS.__dict__, "barrier0": 0.5, "bound_push": 0.3, "max_gradient": 7.0})
    reset = ip.iteration_options(changed)
    assert (reset.barrier0, reset.bound_push, reset.max_gradient) == (ip.Options.barrier0, ip.Options.bound_push,
                                                                     ip.Options.max_gradient)
    assert ip.iteration_options(reset) == reset and reset.max_iterations == changed.max_iterations
    state = start(_problem(), Z0, THETA0, changed)
    ours, theirs = advance(_problem(), state, changed, 5), advance(_problem(), state, reset, 5)
    assert int(ours.iterations) == 5
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(theirs)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_a_time_budget_stops_with_the_last_iterate(whole):
    result, slices = _run(_problem(), advance_hook=lambda n: time.sleep(0.05), time_budget=0.12, interruptible=False)
    stopped = int(result.iterations)
    assert ip.Status(int(result.status)) is ip.Status.TIME_LIMIT
    assert 2 <= stopped < int(whole.iterations)  # the first slice, then about 0.12 s of slices
    assert np.isfinite(np.asarray(result.Z)).all() and np.isfinite(float(result.violation))
    reference = _stopped_at(stopped)
    assert ip.Status(int(reference.status)) is ip.Status.MAX_ITERATIONS
    np.testing.assert_allclose(np.asarray(result.Z), np.asarray(reference.Z), rtol=0, atol=1e-12)
    assert float(result.violation) == pytest.approx(float(reference.violation), rel=1e-9, abs=1e-15)


needs_main_thread = pytest.mark.skipif(threading.current_thread() is not threading.main_thread(),
                                       reason="Python delivers SIGINT to the main thread only")


@needs_main_thread
def test_ctrl_c_stops_after_the_running_slice_with_its_iterate(monkeypatch):
    monkeypatch.setattr(stopping, "SLICE_SECONDS", 1e-9)
    before = signal.getsignal(signal.SIGINT)
    result, slices = _run(_problem(), advance_hook=lambda n: n == 2 and signal.raise_signal(signal.SIGINT))
    assert ip.Status(int(result.status)) is ip.Status.INTERRUPTED
    assert len(slices) == 2 and int(result.iterations) == slices[-1]
    reference = _stopped_at(slices[-1])
    np.testing.assert_allclose(np.asarray(result.Z), np.asarray(reference.Z), rtol=0, atol=1e-12)
    assert signal.getsignal(signal.SIGINT) is before  # the user's handler is back


@needs_main_thread
def test_a_second_ctrl_c_aborts_at_once():
    before = signal.getsignal(signal.SIGINT)

    def twice(n):
        signal.raise_signal(signal.SIGINT)
        signal.raise_signal(signal.SIGINT)

    with pytest.raises(KeyboardInterrupt):
        _run(_problem(), advance_hook=twice)
    assert signal.getsignal(signal.SIGINT) is before


class _Owner(Exception):
    pass


@needs_main_thread
def test_without_interruptible_ctrl_c_is_left_to_python():
    """The solve installs no handler of its own: SIGINT reaches whichever handler the process
    had (here one that raises ``_Owner``; the ambient one can differ from Python's default in a
    test worker that ran other tests before)."""

    def owner(signum, frame):
        raise _Owner

    previous = signal.signal(signal.SIGINT, owner)
    try:
        with pytest.raises(_Owner):
            _run(_problem(), advance_hook=lambda n: signal.raise_signal(signal.SIGINT), interruptible=False)
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_batch_stops_together_and_finished_instances_keep_their_status(monkeypatch):
    """Three instances: one stops at its first iteration on a NaN, two still run when the batch
    is interrupted after two slices; those two get INTERRUPTED, the NaN one keeps NAN."""
    monkeypatch.setattr(stopping, "SLICE_SECONDS", 1e-9)
    nlps = jax.tree.map(lambda *x: jnp.stack(x), *[_problem(a) for a in (1.0, 0.5, 1.0)])
    starts = jnp.stack([Z0, Z0, Z0.at[3, 1].set(jnp.nan)])
    bstart = jax.jit(jax.vmap(lambda nlp, z: ip.start(nlp, z, THETA0, OPTIONS)))
    badvance = jax.jit(jax.vmap(lambda nlp, s, until: ip.advance(nlp, s, OPTIONS, until), (0, 0, None)))
    bfinish = jax.jit(jax.vmap(ip.finish, (0, 0, None)))
    calls = []

    def step(state, until):
        calls.append(until)
        state = badvance(nlps, state, until)
        if len(calls) == 2:
            signal.raise_signal(signal.SIGINT)
        return state

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("Python delivers SIGINT to the main thread only")
    result = stopping.run(bstart(nlps, starts), step, lambda s, stopped: bfinish(nlps, s, stopped),
                          OPTIONS.max_iterations)
    statuses = [ip.Status(int(s)) for s in result.status]
    assert statuses == [ip.Status.INTERRUPTED, ip.Status.INTERRUPTED, ip.Status.NAN]
    assert np.asarray(result.iterations).tolist() == [2, 2, 1]
    assert np.isfinite(np.asarray(result.Z[:2])).all()


@pytest.mark.parametrize("budget", [0, -1.0, float("inf"), float("nan"), "10", True])
def test_a_time_budget_must_be_a_positive_number_of_seconds(budget):
    with pytest.raises(ValueError, match="time_budget must be a positive number of seconds"):
        stopping.check_budget(budget)
