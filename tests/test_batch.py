"""Batched solves (``jaxmm.batch``, ``jaxmm.schedule``): the queue is the single solves bit for
bit; the vmapped slots give the answers of separate solves, refill a slot from the queue as its
instance stops and keep each instance's answer while the others run; a time budget stops both;
the sampler is seeded and stays in the boxes, the summary ranks and groups, and mismatched
batches are rejected with errors that name the problem.

Every solving test runs 14-knot tasks of one structure: standing still (x_N = x_0 at the
standing CoM) from the published guess and from a sampled guess, and the reduced take-off of
``conftest`` (other targets and times; it flies), against the same three solved one by one (the
command line's compiled take-off, which CI's main job fills the cache with).

A vmapped batch and a single solve round differently (batched and unbatched XLA kernels), by
1e-16 at the first iteration; the nonconvex iteration amplifies it (≈ 1e-10 after 40 iterations
on the take-off, 4e-6 at iteration 17 of the standing task below), and over hundreds of
iterations the two may stop a few iterations apart at points equal within the solver's
stationarity tolerance. With the slacks starting at the pushed guess (the default) the early
phase amplifies faster: at EARLY = 10 the two have differed by 3.8e-8 at iteration 8, and a
rounding-level change of the solver made the batch refine one step once more than the single
solve at iteration 6 (then 1.2e-6 apart), and on the take-off the batch made one block solve less at
iteration 3 (2.3e-7 apart). So the first ``EARLY`` iterations must agree to ``SAME_PATH`` and the
answers to ``SAME_ANSWER``.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmm
from jaxmm import analysis, batch, compilation, schedule, solve, tasks
from jaxmm.solver import interior_point as ip
from jaxmm.transcription.constraints import variable_bounds

from conftest import REDUCED_TAKE_OFF, free_compiled_programs

EARLY = 2  # iterations over which a batch and a single solve follow the same path
SAME_PATH = 1e-8  # relative, on every history column over the first EARLY iterations
SAME_ANSWER = 1e-4  # relative objective: the solver's stationarity tolerance
ROUNDING = 1e-14  # the same guess computed compiled and eagerly


@pytest.fixture
def _free_compiled_programs_after():
    """For the tests that compile programs of their own (the sliced batches): this file's batch,
    single solves and sliced batches kept together in one process passed ``vm.max_map_count``
    (a ``pytest -m slow`` run has died at the second sliced batch). Not after every
    test: the sharing test counts the batch's compiled programs."""
    yield
    free_compiled_programs()


@pytest.fixture(scope="module")
def task():
    """Standing still for 14 knots: x_0 = x_N = the standing CoM. The standing base orientation
    is 0.008 from the identity, so the final orientation is given 0.02 (as in test_analysis)."""
    robot = jaxmm.load_ironcub()
    com = jaxmm.com_position(robot.model, robot.standing_configuration)
    return tasks.scenario("take_off", knots=14, initial_com=com, final_com=com, final_orientation_tolerance=0.02)


@pytest.fixture(scope="module")
def problems(task):
    """(batched tasks, batched guesses): standing from the published and from a sampled guess,
    the reduced take-off from its published guess."""
    take_off = tasks.scenario("take_off", **REDUCED_TAKE_OFF)
    sampled = batch.instance(batch.sample_guesses(task, jax.random.key(1), 1, joint_scale=0.05, thrust_scale=5.0), 0)
    guesses = [tasks.initial_guess(task), sampled, tasks.initial_guess(take_off)]
    return batch.stack_tasks([task, task, take_off]), batch.stack_trajectories(guesses)


@pytest.fixture(scope="module")
def solved(problems):
    return batch.solve_batch(*problems, strategy="queue")


SLOW_FIRST = [2, 0, 1]  # the take-off, then the two standing solves


@pytest.fixture(scope="module")
def slotted(problems):
    """(the batch in SLOW_FIRST order in two vmapped slots, the ``BatchProgress`` reports): the
    take-off holds one slot while the standing solves pass through the other."""
    reports = []
    reorder = lambda tree: jax.tree.map(lambda leaf: leaf[np.array(SLOW_FIRST)], tree)  # noqa: E731
    result = batch.solve_batch(reorder(problems[0]), reorder(problems[1]), strategy="slots", slots=2,
                               progress=reports.append)
    return result, reports


@pytest.fixture(scope="module")
def singles(problems):
    """The instances solved one by one (``instance`` of a stacked task has the task's own leaf
    types, so this is the compiled solve of ``solve_task(task)``)."""
    stacked, guesses = problems
    return [solve.solve_task(batch.instance(stacked, i), batch.instance(guesses, i))
            for i in range(batch.batch_size(guesses))]


def _with_nan(guess):
    knots = guess.knots
    return dataclasses.replace(guess, knots=dataclasses.replace(
        knots, joint_positions=knots.joint_positions.at[3, 0].set(jnp.nan)))


# ----------------------------------------------------------------------------------- solving


def test_the_queue_is_the_single_solves_bit_for_bit_and_compiles_nothing_more(problems, solved, singles):
    """The queue runs ``solve_task``'s own compiled programs: after the single solves, a queued
    batch of the same instances loads no program and returns the same numbers exactly."""
    assert [r.status for r in singles] == [ip.Status.CONVERGED] * 3
    loaded = compilation.loaded_programs()
    again = batch.solve_batch(*problems, strategy="queue")
    assert compilation.loaded_programs() == loaded
    for result in (solved, again):
        for i, single in enumerate(singles):
            mine = batch.instance(result, i)
            for a, b in zip(jax.tree.leaves(mine), jax.tree.leaves(single)):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
            assert analysis.validate(batch.instance(problems[0], i), mine.trajectory).ok


def test_the_processes_give_the_single_solves_answers(problems, singles):
    """Two worker processes (each pinned to a core this process may use: its kernels round as
    one core does, so to the batch tolerance rather than bit for bit), each taking the next
    instance as it finishes one."""
    ended = []
    results = schedule.run_processes(*problems, solve.DEFAULT_OPTIONS, lambda j, r: ended.append(j), workers=2)
    assert sorted(ended) == [0, 1, 2]
    for i, (mine, single) in enumerate(zip(results, singles)):
        assert mine.status is single.status is ip.Status.CONVERGED
        np.testing.assert_allclose(np.asarray(mine.solution.history[:EARLY]),
                                   np.asarray(single.solution.history[:EARLY]), rtol=SAME_PATH)
        assert float(mine.solution.objective) == pytest.approx(float(single.solution.objective), rel=SAME_ANSWER)
        assert analysis.validate(batch.instance(problems[0], i), mine.trajectory).ok


def test_the_default_strategy_follows_the_backend_and_the_cores(monkeypatch):
    """Accelerators vmap slots; a CPU spreads more than one instance over its cores, and runs one
    instance, or any number on one core, in the calling process."""
    gpu, cpu = type("Device", (), {"platform": "gpu"})(), type("Device", (), {"platform": "cpu"})()
    monkeypatch.setattr(schedule, "cores", lambda: [0, 1])
    assert [schedule.default_strategy(None, 8, [gpu]), schedule.default_strategy(None, 8, [cpu]),
            schedule.default_strategy(None, 1, [cpu])] == ["slots", "processes", "queue"]
    monkeypatch.setattr(schedule, "cores", lambda: [0])
    assert schedule.default_strategy(None, 8, [cpu]) == "queue"
    assert schedule.default_strategy("slots", 8, [cpu]) == "slots"


def test_the_slots_give_the_single_solves_answers(problems, slotted, singles):
    result, _ = slotted
    for position, i in enumerate(SLOW_FIRST):
        mine, single = batch.instance(result, position), singles[i]
        assert mine.status is single.status is ip.Status.CONVERGED
        np.testing.assert_allclose(np.asarray(mine.solution.history[:EARLY]),
                                   np.asarray(single.solution.history[:EARLY]), rtol=SAME_PATH)
        assert float(mine.solution.objective) == pytest.approx(float(single.solution.objective), rel=SAME_ANSWER)
        assert float(mine.solution.violation) <= solve.DEFAULT_OPTIONS.tolerance
        assert analysis.validate(batch.instance(problems[0], i), mine.trajectory).ok


def test_a_freed_slot_takes_the_next_guess_while_the_slow_instance_runs(slotted):
    """Three instances in two slots, the slow take-off first: the first standing solve ends
    while the take-off runs, and the queued one takes its slot at once (two running, none queued);
    the reports count the ended instances, with the best objective of the converged ones."""
    result, reports = slotted
    iterations = np.asarray(result.solution.iterations)
    assert iterations[1] < iterations[0] and iterations[2] < iterations[0]
    assert (reports[0].index, reports[0].finished, reports[0].running, reports[0].queued) == (1, 1, 2, 0)
    assert sorted(r.index for r in reports[1:]) == [0, 2] and [r.finished for r in reports] == [1, 2, 3]
    assert (reports[-1].running, reports[-1].queued) == (0, 0)
    objective = np.asarray(result.solution.objective)
    assert reports[0].best == objective[1] and reports[-1].best == objective.min()
    assert reports[0].schedules == 1 and reports[-1].schedules == 2  # standing; the take-off flies
    assert str(reports[-1]).startswith("3 finished, 0 running, 0 queued; best objective ")


def test_instances_that_stop_keep_their_answer_while_the_others_run(task, slotted):
    """Each standing solve keeps the state it stopped in while the take-off's slot runs on: its
    history ends where it stopped and its answer is a valid standing trajectory."""
    result, _ = slotted
    iterations = np.asarray(result.solution.iterations)
    history = np.asarray(result.solution.history)
    for i, stop in enumerate(iterations):
        assert np.all(np.isfinite(history[i, :stop])) and np.all(np.isnan(history[i, stop:]))
    for i in (1, 2):
        standing = batch.instance(result, i)
        # The converged point is the one recorded at its last iteration, not a later one.
        assert float(standing.solution.objective) == pytest.approx(history[i, iterations[i] - 1, 0], rel=1e-12)
        report = analysis.validate(task, standing.trajectory)
        assert report.ok, str(report)


def test_nan_guesses_are_refused_at_the_boundary_and_stop_at_once_below_it(task, problems, slotted):
    """A guess with a NaN is refused by solve_batch, naming the instances; below the boundary
    (the slots' own programs, compiled for ``slotted``) such instances stop at once with status
    NAN, as a single solve does."""
    guess = _with_nan(batch.instance(problems[1], 0))
    good = batch.instance(problems[1], 0)
    with pytest.raises(ValueError, match=r"joint_positions has non-finite entries .* in instances \[1, 2\]"):
        batch.solve_batch(task, [good, guess, guess])
    ended = []
    results = schedule.run_slots(batch.broadcast_task(task, 2), batch.stack_trajectories([guess, guess]),
                                 solve.DEFAULT_OPTIONS, 2, lambda j, r: ended.append(j))
    assert sorted(ended) == [0, 1]
    assert [r.status for r in results] == [ip.Status.NAN] * 2
    assert [int(r.solution.iterations) for r in results] == [1, 1]


def test_a_time_budget_stops_the_queue_on_its_path(problems, solved):
    """A budget of 1 ms: the first instance stops after at most two iterations (the first slice,
    then one) with status TIME_LIMIT and the history of its full solve; the queued ones stop
    unstarted, at their guesses."""
    stopped = batch.solve_batch(*problems, strategy="queue", time_budget=1e-3)
    assert [ip.Status(int(s)) for s in stopped.solution.status] == [ip.Status.TIME_LIMIT] * 3
    iterations = np.asarray(stopped.solution.iterations)
    assert iterations[0] <= 2 and list(iterations[1:]) == [0, 0]
    np.testing.assert_array_equal(np.asarray(stopped.solution.history)[0, :iterations[0]],
                                  np.asarray(solved.solution.history)[0, :iterations[0]])
    assert all(np.all(np.isfinite(np.asarray(leaf))) for leaf in jax.tree.leaves(stopped.trajectory))


def test_a_time_budget_stops_the_slots_after_their_first_slice(problems, slotted):
    """The budget counts from the end of the first slice (which compiles): the two instances in
    slots stop after one more slice of ``SLICE_ITERATIONS``, on the path of the full batch; the
    queued one stops unstarted."""
    full, _ = slotted
    reorder = lambda tree: jax.tree.map(lambda leaf: leaf[np.array(SLOW_FIRST)], tree)  # noqa: E731
    stopped = batch.solve_batch(reorder(problems[0]), reorder(problems[1]), strategy="slots", slots=2,
                                time_budget=1e-3)
    assert [ip.Status(int(s)) for s in stopped.solution.status] == [ip.Status.TIME_LIMIT] * 3
    ran = 2 * schedule.SLICE_ITERATIONS
    assert list(np.asarray(stopped.solution.iterations)) == [ran, ran, 0]
    np.testing.assert_allclose(np.asarray(stopped.solution.history)[:2, :ran],
                               np.asarray(full.solution.history)[:2, :ran], rtol=SAME_PATH)


def test_a_broadcast_task_has_the_leaf_types_of_stacked_tasks(task):
    """So that a multi-start batch (one task, broadcast) and a batch of tasks share one compiled solve:
    a weakly typed leaf (a float given in Python) would make jit compile another."""
    other = tasks.scenario("take_off", **{**REDUCED_TAKE_OFF, "final_com": (0.0, 0.0, 0.78)})
    assert jax.tree.map(jax.typeof, batch.broadcast_task(task, 2)) == jax.tree.map(
        jax.typeof, batch.stack_tasks([task, other]))


def test_the_default_guesses_of_a_batch_of_tasks_are_the_published_ones(task):
    other = tasks.scenario("take_off", **{**REDUCED_TAKE_OFF, "final_com": (0.0, 0.0, 0.78)})
    published = batch.published_guesses(batch.stack_tasks([task, other]))
    for i, one in enumerate((task, other)):
        for a, b in zip(jax.tree.leaves(batch.instance(published, i)), jax.tree.leaves(tasks.initial_guess(one))):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=ROUNDING, atol=ROUNDING)


# ----------------------------------------------------------------------------------- summary


def test_the_summary_ranks_by_objective_and_groups_by_schedule(task, solved):
    """Three converged instances rank by objective; the two standing solutions keep every
    corner on the ground (one schedule, validate's: no flight), the take-off flies at its end
    (another); schedules are numbered by their best member."""
    summary = batch.summarise(task, solved)
    objective = np.asarray(solved.solution.objective)
    order = sorted(range(3), key=lambda i: objective[i])
    assert [r.index for r in summary.ranking] == order
    assert [r.status for r in summary.ranking] == [ip.Status.CONVERGED] * 3 and summary.best.index == order[0]
    assert len(summary.schedules) == 2 and summary.best.schedule == 0
    for result in summary.ranking:
        schedule = summary.schedules[result.schedule]
        assert result.index in schedule.members
        airborne = analysis.airborne_corners(batch.instance(solved, result.index).trajectory)
        np.testing.assert_array_equal(schedule.airborne, airborne)
    ranks = {r.index: r.schedule for r in summary.ranking}
    assert ranks[0] == ranks[1] != ranks[2]
    on_the_ground, flying = summary.schedules[ranks[0]], summary.schedules[ranks[2]]
    report = analysis.validate(task, batch.instance(solved, 0).trajectory)
    assert not on_the_ground.airborne.any() and on_the_ground.flight_knots == report.flight_knots == ()
    assert flying.airborne.any() and flying.flight_knots[-1] == task.n_knots - 1 and flying.members == (2,)
    assert on_the_ground.members == tuple(i for i in order if i != 2)
    text = str(summary)
    assert text.startswith("3 instances: 3 converged, 0 feasible")
    number = ranks[0] + 1
    assert f"schedule {number}: instances " + ", ".join(map(str, on_the_ground.members)) + "; flight knots none" in text
    assert text.count("l_sole_1") == len(summary.schedules)  # each schedule printed once
    assert f"  l_sole_1  {'#' * task.n_knots}" in text


def test_the_ranking_puts_converged_then_feasible_then_the_rest(task, solved):
    """Numbers made up on the real batch: a feasible run stopped at the iteration limit ranks
    after a converged one with a higher objective, and an infeasible one last."""
    made_up = dataclasses.replace(solved, solution=dataclasses.replace(
        solved.solution,
        status=jnp.array([int(ip.Status.MAX_ITERATIONS), int(ip.Status.CONVERGED), int(ip.Status.STALLED)]),
        objective=jnp.array([1.0, 5.0, 0.5]),
        violation=jnp.array([1e-8, 1e-9, 1e-3]),
    ))
    summary = batch.summarise(task, made_up)
    assert [r.index for r in summary.ranking] == [1, 0, 2]
    assert [r.status for r in summary.ranking] == [ip.Status.CONVERGED, ip.Status.MAX_ITERATIONS, ip.Status.STALLED]
    assert str(summary).startswith("3 instances: 1 converged, 1 feasible")


# ----------------------------------------------------------------------------------- sampler


def test_the_sampler_is_deterministic_for_a_key_and_stays_in_the_boxes(task):
    first = batch.sample_guesses(task, jax.random.key(7), 5)
    again = batch.sample_guesses(task, jax.random.key(7), 5)
    other = batch.sample_guesses(task, jax.random.key(8), 5)
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(again)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.allclose(np.asarray(first.knots.joint_positions), np.asarray(other.knots.joint_positions))
    assert batch.batch_size(first) == 5
    lower, upper = variable_bounds(task)
    for value, lo, hi in zip(jax.tree.leaves(first), jax.tree.leaves(lower), jax.tree.leaves(upper)):
        value, lo, hi = (np.asarray(v) for v in (value, lo, hi))
        assert np.all(value >= lo) and np.all(value <= hi)
    # The instances differ from each other in every perturbed variable.
    for leaf in (first.knots.joint_positions, first.knots.contact_points, first.knots.thrust, first.total_time):
        assert np.ptp(np.asarray(leaf), axis=0).max() > 0


def test_the_sampler_perturbs_what_its_scales_say(task):
    published = tasks.initial_guess(task)
    lower, upper = variable_bounds(task)
    clipped = jax.tree.map(jnp.clip, published, lower, upper)
    still = batch.sample_guesses(task, jax.random.key(0), 2, joint_scale=0.0, horizon_scale=0.0, contact_shift=0.0,
                                 contact_lift=0.0, thrust_scale=0.0)
    for i in range(2):
        for a, b in zip(jax.tree.leaves(batch.instance(still, i)), jax.tree.leaves(clipped)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=ROUNDING, atol=ROUNDING)
    # Only the posture: the same shift at every knot, nothing else moves.
    posture = batch.instance(batch.sample_guesses(task, jax.random.key(0), 1, horizon_scale=0.0, contact_shift=0.0,
                                                  contact_lift=0.0, thrust_scale=0.0), 0)
    shift = np.asarray(posture.knots.joint_positions - clipped.knots.joint_positions)
    assert np.abs(shift).max() > 0
    inside = np.all((np.asarray(posture.knots.joint_positions) > np.asarray(lower.knots.joint_positions))
                    & (np.asarray(posture.knots.joint_positions) < np.asarray(upper.knots.joint_positions)), axis=0)
    np.testing.assert_allclose(shift[:, inside], np.broadcast_to(shift[0, inside], shift[:, inside].shape), atol=1e-15)
    np.testing.assert_allclose(np.asarray(posture.knots.thrust), np.asarray(clipped.knots.thrust), rtol=ROUNDING)
    # The corners of a sole move together; knot 0 stays on the ground.
    contacts = batch.instance(batch.sample_guesses(task, jax.random.key(3), 1, joint_scale=0.0, horizon_scale=0.0,
                                                   thrust_scale=0.0), 0)
    offset = np.asarray(contacts.knots.contact_points - clipped.knots.contact_points)  # (N + 1, 8, 3)
    for sole in (slice(0, 4), slice(4, 8)):  # l_sole_1..4, r_sole_1..4
        np.testing.assert_allclose(offset[:, sole], np.broadcast_to(offset[:, sole][:, :1], offset[:, sole].shape),
                                   atol=1e-15)
    assert not np.allclose(offset[:, 0], offset[:, 4])
    np.testing.assert_array_equal(offset[0, :, 2], 0.0)
    assert np.all(offset[-1, :, 2] > 0)


def test_the_sampler_rejects_bad_arguments(task):
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="n must be a positive integer"):
        batch.sample_guesses(task, key, 0)
    with pytest.raises(ValueError, match="joint_scale must be finite and non-negative"):
        batch.sample_guesses(task, key, 2, joint_scale=-0.1)
    with pytest.raises(ValueError, match=r"horizon_scale must be in \[0, 1\]"):
        batch.sample_guesses(task, key, 2, horizon_scale=2.0)
    with pytest.raises(TypeError, match="key must be one JAX PRNG key"):
        batch.sample_guesses(task, 0, 2)
    with pytest.raises(TypeError, match="key must be one JAX PRNG key"):
        batch.sample_guesses(task, jax.random.split(key, 2), 2)
    small = tasks.initial_guess(tasks.scenario("take_off", knots=10))
    with pytest.raises(ValueError, match=r"around\.knots\.com has shape \(11, 3\); the task needs \(15, 3\)"):
        batch.sample_guesses(task, key, 2, around=small)


# ------------------------------------------------------------------------------------ errors


def test_tasks_of_different_structure_cannot_be_stacked(task):
    with pytest.raises(ValueError, match=r"task 1 cannot be batched with task 0: .*task\.n_intervals: 14 vs 10"):
        batch.stack_tasks([task, tasks.scenario("take_off", knots=10)])
    with pytest.raises(ValueError, match=r"task 2 cannot .*task\.robot\.jet_frames: differs.*task\.name: 'take_off' vs 'jumping'"):
        batch.stack_tasks([task, task, tasks.scenario("jumping", knots=14)])
    with pytest.raises(ValueError, match=r"cannot stack an empty list \(no task given\)"):
        batch.stack_tasks([])
    with pytest.raises(TypeError, match="task 1 is a Trajectory, not a Task"):
        batch.stack_tasks([task, tasks.initial_guess(task)])
    with pytest.raises(TypeError, match="expected a list of Tasks to stack"):
        batch.stack_tasks(task)
    stacked = batch.stack_tasks([task, tasks.scenario("take_off", **REDUCED_TAKE_OFF, final_com=(0.0, 0.0, 0.78))])
    assert batch.batch_size(stacked) == 2
    np.testing.assert_array_equal(np.asarray(stacked.params.final_com[:, 2]), [float(task.params.final_com[2]), 0.78])


def test_mismatched_batches_are_rejected_before_compiling(task, problems):
    guesses = problems[1]
    one = batch.instance(guesses, 0)
    with pytest.raises(ValueError, match=r"guesses must have a leading batch axis \(total_time of shape \(B,\)\)"):
        batch.solve_batch(task, one)
    small = batch.sample_guesses(tasks.scenario("take_off", knots=10), jax.random.key(0), 2)
    with pytest.raises(ValueError, match=r"guesses\.knots\.com has shape \(2, 11, 3\); the task needs \(2, 15, 3\)"):
        batch.solve_batch(task, small)
    with pytest.raises(ValueError, match="guess 1 cannot be batched with guess 0: guess.knots.com has shape"):
        batch.solve_batch(task, [one, batch.instance(small, 0)])
    with pytest.raises(ValueError, match="3 guesses for a batch of 2 tasks"):
        batch.solve_batch([task, task], guesses)
    with pytest.raises(ValueError, match="time_budget must be a positive number of seconds, got -1"):
        batch.solve_batch(task, guesses, time_budget=-1)
    with pytest.raises(ValueError, match="a sharded batch is one call: it takes no strategy, progress, time_budget"):
        batch.solve_batch(task, guesses, mesh=batch.batch_mesh(), time_budget=10.0)
    with pytest.raises(ValueError, match=r"strategy must be one of \('queue', 'processes', 'slots'\)"):
        batch.solve_batch(task, guesses, strategy="vmap")
    with pytest.raises(ValueError, match="strategy 'processes' takes no time_budget or interrupt"):
        batch.solve_batch(task, guesses, strategy="processes", time_budget=10.0)
    with pytest.raises(ValueError, match="slots must be a positive integer, got 0"):
        batch.solve_batch(task, guesses, strategy="slots", slots=0)
    with pytest.raises(ValueError, match="3 guesses for a batch of 2 tasks"):
        batch.solve_batch(batch.stack_tasks([task, task]), guesses)
    with pytest.raises(ValueError, match=r"a batch of one task needs its guesses \(see sample_guesses\)"):
        batch.solve_batch(task)
    with pytest.raises(TypeError, match="tasks must be a Task, a batched Task or a list of Tasks, got int"):
        batch.solve_batch(3, guesses)
    with pytest.raises(TypeError, match="guesses must be a batched Trajectory or a list of Trajectories"):
        batch.solve_batch(task, {"total_time": jnp.ones(3)})
    ragged = dataclasses.replace(guesses, total_time=jnp.ones(2))
    with pytest.raises(ValueError, match=r"guesses\.knots\.com has shape \(3, 15, 3\); the task needs \(2, 15, 3\)"):
        batch.solve_batch(task, ragged)
    with pytest.raises(IndexError, match="instance 3 is out of range for a batch of 3"):
        batch.instance(guesses, 3)
    with pytest.raises(ValueError, match="different leading sizes"):
        batch.batch_size(ragged)
