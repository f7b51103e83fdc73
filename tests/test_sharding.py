"""Batched solves sharded over devices (``batch.batch_mesh``, ``solve_batch(..., mesh=...)``),
on two simulated CPU devices (``XLA_FLAGS=--xla_force_host_platform_device_count=2``, which
must be set before JAX starts, hence a subprocess): the sharded batch gives the answers of the
unsharded one (a weight sweep from sampled guesses: multi-start runs the same program) up to
rounding, bit-identical from run to run, its answer split over both devices; a batch that does
not split evenly is refused. On CPU devices each device runs its instances one after another
(see ``batch._vectorised_on``: batched LAPACK kernels hang there), so the reference is the
unsharded batch run the same way (``strategy="queue"``: the single solves).

Not bit-identical to it: XLA compiles the per-device program of ``shard_map`` differently from
the plain jit (measured: the unsharded batch, a one-device mesh and single solves agree bit for
bit; two devices differ from all of them, and from the unsharded batches of each device's two
instances, by rounding: the first history rows equal, objectives after 15 iterations within
1.3e-9 with or without multithreaded Eigen; the differences can grow about a thousandfold per
iteration from the third: 6e-11 at the fourth, 1.7e-5 after 15, as single solves' paths part
under rounding-level changes)."""

import json
import os
import subprocess
import sys
import textwrap


SCRIPT = textwrap.dedent("""
    import dataclasses, json
    import jax
    import numpy as np
    from jaxmm import batch, solve, tasks

    assert len(jax.devices()) == 2, jax.devices()
    task = tasks.scenario("take_off", knots=3)
    options = dataclasses.replace(solve.DEFAULT_OPTIONS, max_iterations=15)
    mesh = batch.batch_mesh()

    def same(a, b):
        return all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
                   for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))

    # Multi-start and sweep run the same sharded program (solve_batch broadcasts its task), so
    # one sweep from sampled guesses covers both: two compilations in all.
    guesses = batch.sample_guesses(task, jax.random.key(0), 4)
    sweep = [dataclasses.replace(task, weights=dataclasses.replace(task.weights, thrust=task.weights.thrust * f))
             for f in (0.5, 1.0, 2.0, 4.0)]
    plain = batch.solve_batch(sweep, guesses, options, strategy="queue")
    sharded = batch.solve_batch(sweep, guesses, options, mesh=mesh)
    again = batch.solve_batch(sweep, guesses, options, mesh=mesh)
    objectives = [np.asarray(r.solution.objective) for r in (plain, sharded)]
    try:
        batch.solve_batch(task, batch.sample_guesses(task, jax.random.key(1), 3), options, mesh=mesh)
        uneven = "no error"
    except ValueError as error:
        uneven = str(error)
    print(json.dumps(dict(
        repeatable=same(sharded, again),
        objective_difference=float(np.max(np.abs(objectives[1] - objectives[0]) / np.abs(objectives[0]))),
        # Per iteration, the largest relative difference of objective, violation, stationarity and μ.
        history_differences=np.nan_to_num(np.max(
            np.abs(np.asarray(sharded.solution.history)[..., :4] - np.asarray(plain.solution.history)[..., :4])
            / np.maximum(np.abs(np.asarray(plain.solution.history)[..., :4]), 1e-300), axis=(0, 2))).tolist(),
        plain_statuses=[int(s) for s in plain.solution.status],
        plain_iterations=[int(i) for i in plain.solution.iterations],
        distinct_objectives=len(set(np.asarray(plain.solution.objective).tolist())),
        devices=len(sharded.solution.Z.sharding.device_set),
        statuses=[int(s) for s in sharded.solution.status],
        iterations=[int(i) for i in sharded.solution.iterations],
        uneven=uneven,
    )))
""")


def test_a_batch_sharded_over_two_devices_gives_the_unsharded_answers():
    # The suite's XLA flags (conftest) kept, so that the subprocess compiles as fast as the tests do.
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip()
    env = dict(os.environ, XLA_FLAGS=flags)
    done = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=1500)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["devices"] == 2, result
    assert result["repeatable"], result
    assert result["statuses"] == result["plain_statuses"] and result["iterations"] == result["plain_iterations"], result
    # The same path, rounding apart, amplified from one iteration to the next (take-off N = 3, seen:
    # 3e-15, 9e-14, 4e-11, 6e-11, then 9e-8 at the fifth and 1.7e-5 after 15; on another CPU
    # 4e-16, 7e-14, 7e-9, 4.6e-7, then ≈ 6e-7).
    differences = result["history_differences"]
    assert max(differences[:2]) <= 1e-12 and max(differences[:4]) <= 1e-6, result
    assert result["objective_difference"] <= 1e-3, result
    assert result["distinct_objectives"] == 4, result  # four different problems were solved
    assert all(0 < i <= 15 for i in result["iterations"]), result
    assert "does not split evenly over 2 devices" in result["uneven"], result
