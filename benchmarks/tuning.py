"""Weight tuning study: recover hidden cost weights from a reference trajectory.

A reference take-off is solved with hidden weights (by default com_vel and final_thrust scaled
by --hidden); ``tuning.tune_weights`` then starts from the published weights and minimises the
normalised squared distance between its optimal trajectory and the reference (CoM path and
thrust profile), by gradients of the optimum (implicit differentiation, one adjoint solve per
step) and Adam on the log-weights, each solve warm-started from the previous one.

Printed: per step the loss, the solver's iterations, the weights and their ratio to the hidden
ones, then the wall time of the study (compile included) and how close the recovered weights
are. --json writes the history. Run by hand:

    python benchmarks/tuning.py [--knots 14] [--steps 30] [--rate 0.1] [--hidden 3 0.3] [--json out.json]

The task is the take-off with --knots knots and the published 3.5–7 s horizon.
"""

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"  # before numpy is imported

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

import jaxmm  # noqa: E402, F401  (float64)
from machine import machine_lines  # noqa: E402
from jaxmm import solve, tasks, tuning  # noqa: E402
from jaxmm.solver import interior_point as ip  # noqa: E402

NAMES = ("com_vel", "final_thrust")


def take_off(knots):
    return tasks.scenario("take_off", knots=knots, keep_horizon=True)


def with_weights(task, values):
    return dataclasses.replace(task, weights=dataclasses.replace(
        task.weights, **{n: jnp.asarray(v, dtype=float) for n, v in values.items()}))


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--knots", type=int, default=14)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--rate", type=float, default=0.1, help="Adam learning rate on the log-weights")
    parser.add_argument("--hidden", type=float, nargs=len(NAMES), default=(3.0, 0.3),
                        help=f"factors of the published {', '.join(NAMES)} that made the reference")
    parser.add_argument("--json", help="write the history here")
    args = parser.parse_args()
    for line in machine_lines(["jax", "optax"]):
        print(line)

    task = take_off(args.knots)
    published = {n: float(getattr(task.weights, n)) for n in NAMES}
    hidden = {n: published[n] * f for n, f in zip(NAMES, args.hidden)}
    start = time.perf_counter()
    reference = solve.solve_task(with_weights(task, hidden))
    print(f"reference: hidden weights {hidden}, {reference.status.name}, {int(reference.solution.iterations)} iterations")
    if reference.status is not ip.Status.CONVERGED:
        sys.exit("the reference solve did not converge: nothing to recover")
    com_ref = reference.trajectory.knots.com
    thrust_ref = reference.trajectory.knots.thrust
    com_scale = float(jnp.max(jnp.abs(com_ref - com_ref[0]))) or 1.0
    thrust_scale = float(jnp.max(jnp.abs(thrust_ref))) or 1.0

    def loss(task, trajectory):
        """Mean squared distance to the reference: CoM path [per max displacement] and thrust
        [per max thrust]."""
        knots = trajectory.knots
        return (jnp.mean(((knots.com - com_ref) / com_scale) ** 2)
                + jnp.mean(((knots.thrust - thrust_ref) / thrust_scale) ** 2))

    first = solve.solve_task(task)
    result = tuning.tune_weights(task, loss, names=NAMES, optimizer=optax.adam(args.rate), steps=args.steps,
                                 warm_start=first)
    elapsed = time.perf_counter() - start
    print()
    print(f"{'step':>4}  {'loss':>11}  {'it.':>4}  " + "  ".join(f"{n:>12}  {'/ hidden':>8}" for n in NAMES))
    for k, (value, logs, iterations) in enumerate(zip(result.loss, result.log_weights, result.iterations)):
        weights = np.exp(logs)
        print(f"{k:4d}  {value:11.4e}  {int(iterations):4d}  "
              + "  ".join(f"{w:12.5g}  {w / hidden[n]:8.4f}" for w, n in zip(weights, NAMES)))
    recovered = {n: float(getattr(result.weights, n)) for n in NAMES}
    print()
    print(f"stopped: {result.stopped}; wall time {elapsed:.1f} s (compilation included)")
    print("recovered / hidden: " + ", ".join(f"{n} {recovered[n] / hidden[n]:.4f}" for n in NAMES)
          + f"; loss {result.loss[0]:.3e} → {result.loss.min():.3e}")
    if args.json:
        with open(args.json, "w") as out:
            json.dump(dict(knots=args.knots, hidden=hidden, published=published, recovered=recovered,
                           loss=result.loss.tolist(), log_weights=result.log_weights.tolist(),
                           iterations=result.iterations.tolist(), stopped=result.stopped, seconds=elapsed), out, indent=1)


if __name__ == "__main__":
    main()
