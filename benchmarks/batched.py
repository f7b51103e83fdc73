"""Multi-start take-off: B sampled guesses solved by ``jaxmm.batch.solve_batch`` with each
strategy, against one solve, every run in a fresh Python process so that each pays its own
compiling (JAX's persistent cache off).

The task is ``tasks.scenario("take_off", knots=N, keep_horizon=True)`` (N = 14 by default: the
published 3.5–7 s horizon) on the default iRonCub; the guesses are
``batch.sample_guesses(task, jax.random.key(--seed), B)`` with the sampler's default scales
(every B takes the first B of one sampled set, so the batches are nested).

What is measured (wall clock, compiling included, in a fresh process each):

* one solve: ``solve_task(task, guess 0)``;
* for each strategy (--strategies, default "queue" and "processes"; "slots" is the vmapped
  batch, for accelerators) and each B (--sizes, default 1 16 64): ``solve_batch(task, guesses, strategy=…)``
  (slots: --slots, default ``batch.DEFAULT_SLOTS``), its wall time, its ratio to one solve (the
  goal: ≤ 10× for B = 16, ≤ 40× for B = 64 on a 2-core CPU), the time per instance, and the
  instances' iterations and statuses;
* agreement: every instance of every batch against the same guess in the "queue" batch of the
  largest B (relative objective difference, statuses, iterations).

Pin the process to cores with ``taskset`` to say what a machine of that many cores does; XLA's
thread pool is left at its default (the cores the process may use).

Usage: python benchmarks/batched.py [--knots 14] [--sizes 1 16 64] [--strategies queue processes slots]
       [--slots S] [--seed 0]
"""

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"  # before numpy is imported

import argparse  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from machine import format_time, log, machine_lines, probe, render  # noqa: E402

RUN = """
import json, sys, time
began = time.perf_counter()
import jax
from jaxmm import batch, solve, tasks
knots, size, seed, strategy, slots = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], int(sys.argv[5])
task = tasks.scenario("take_off", knots=knots, keep_horizon=True)
guesses = jax.tree.map(lambda leaf: leaf[:size], batch.sample_guesses(task, jax.random.key(seed), size))
imported = time.perf_counter()
if strategy == "one":
    result = jax.tree.map(lambda leaf: leaf[None], solve.solve_task(task, batch.instance(guesses, 0)))
else:
    result = batch.solve_batch(task, guesses, strategy=strategy, slots=slots)
jax.block_until_ready(result)
s = result.solution
print("PROBE " + json.dumps(dict(seconds=time.perf_counter() - imported, setup=imported - began,
      status=s.status.tolist(), iterations=s.iterations.tolist(), objective=s.objective.tolist())))
"""


def statuses(codes):
    from jaxmm.solver.interior_point import Status

    names = [Status(int(c)).name.lower() for c in codes]
    return ", ".join(f"{name} ×{names.count(name)}" for name in dict.fromkeys(names))


def agreement(run, reference):
    """(max relative objective difference, statuses equal, iterations equal) against the
    reference run's instances of the same guesses."""
    n = len(run["objective"])
    a, b = np.asarray(run["objective"]), np.asarray(reference["objective"][:n])
    worst = float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-300)))
    return worst, run["status"] == reference["status"][:n], run["iterations"] == reference["iterations"][:n]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--knots", type=int, default=14, help="N (default 14)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 16, 64], help="batch sizes B")
    parser.add_argument("--strategies", nargs="+", default=["queue", "processes"], choices=["queue", "processes", "slots"])
    parser.add_argument("--slots", type=int, default=64, help="slots of the 'slots' strategy")
    parser.add_argument("--seed", type=int, default=0, help="seed of sample_guesses")
    args = parser.parse_args()
    if min(args.sizes) < 1:
        parser.error("batch sizes must be ≥ 1")
    started = time.perf_counter()
    header = machine_lines(("jax", "jaxlib", "numpy"))
    affinity = len(os.sched_getaffinity(0))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()

    def measure(strategy, size):
        log(f"{strategy}, B = {size}…")
        run = probe(RUN, (args.knots, size, args.seed, strategy, args.slots), f"{strategy} B = {size}",
                    JAX_ENABLE_COMPILATION_CACHE="false")
        log(f"  {format_time(run['seconds'])}: {statuses(run['status'])}")
        return run

    one = measure("one", 1)
    runs = {(strategy, size): measure(strategy, size) for strategy in args.strategies for size in args.sizes}
    reference = max(((s, b) for s, b in runs if s == "queue"), key=lambda k: k[1], default=None)
    rows, checks = [("one solve (solve_task)", 1, format_time(one["seconds"]), "1×", format_time(one["seconds"]),
                     str(one["iterations"][0]), statuses(one["status"]))], []
    for (strategy, size), run in runs.items():
        iterations = np.asarray(run["iterations"])
        name = f"slots ({min(args.slots, size)})" if strategy == "slots" else strategy
        rows.append((name, size, format_time(run["seconds"]), f"{run['seconds'] / one['seconds']:.3g}×",
                     format_time(run["seconds"] / size), f"{iterations.min()}–{iterations.max()} (Σ {iterations.sum()})",
                     statuses(run["status"])))
        if reference is not None and (strategy, size) != reference:
            worst, same_status, same_iterations = agreement(run, runs[reference])
            checks.append(f"{name} B = {size} against queue B = {reference[1]}: objective rel. difference ≤ "
                          f"{worst:.1e}, statuses {'equal' if same_status else 'DIFFER'}, iterations "
                          f"{'equal' if same_iterations else 'DIFFER'}")
    print("\n".join(header))
    print(f"take_off N = {args.knots} (keep_horizon), sample_guesses(seed {args.seed}); commit {commit}; "
          f"{affinity} core(s) allowed; each row a fresh process, compiling included (persistent cache off)")
    print()
    print(render(("strategy", "B", "wall", "wall / one solve", "per instance", "iterations", "statuses"), rows))
    print()
    print("\n".join(checks))
    print(f"\ntotal {time.perf_counter() - started:.0f} s; load average at the end "
          + ", ".join(f"{x:.2f}" for x in os.getloadavg()))


if __name__ == "__main__":
    main()
