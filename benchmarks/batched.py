"""Multi-start take-off: B initial guesses solved at once by one vmapped solve
(``jaxmm.batch.solve_batch``) against the same guesses solved one after another.

The task is ``tasks.scenario("take_off", knots=N)`` (published N = 70; --knots to reduce it,
then the time-step bounds are scaled to keep the published 3.5–7 s horizon) on the default
assembled iRonCub. The guesses are ``batch.sample_guesses(task, jax.random.key(--seed), B)``
with the sampler's default scales; every batch size takes the first B of the largest set, so the
batches are nested and the sequential runs solve the same guesses.

What is measured (wall clock):

* per batch size B (--sizes, default 1 8 32 64): compile time =
  ``programs.batch_solve.lower(tasks, guesses, options).compile()`` with ``tasks`` the task
  broadcast to B (``batch.broadcast_task``, what ``solve_batch`` does) (tracing, lowering and
  XLA compilation; each B is a new compilation), and solve time = median over --repeats calls
  of the compiled executable (``jax.block_until_ready``; compiled ahead of time, no warm-up
  call needed); solve time / B; the iterations of the batch (the loop runs until its slowest
  instance stops: max over instances) and the instances' own iterations (min–max); statuses.
* sequential: the first --sequential guesses (default: the largest B) solved one after another
  with ``programs.compile_solve`` compiled once for one guess (compile reported apart), each call
  timed once; their sum, and their median for "one solve".
* ratios: batch solve time / (one sequential solve), the issue's goal being ≤ 8 for B = 64,
  and the sequential time of the same B guesses / batch solve time (> 1: the batch is faster).
  When --sequential is below B, the sequential time of B guesses is extrapolated as B × the
  median single solve (marked "≈").
* correctness: for the instances solved both ways, the largest relative objective difference
  between the batch and the single solve, and whether statuses and iterations agree.

WARNING: at the published N = 70 one solve takes minutes (≈ 500 s on the loaded 2-core
benchmark machine), so the default run (64 sequential solves, batches up to 64) takes hours; a
batch holds B copies of the solver state (the Hessian blocks alone are 71 × 178 × 178 numbers,
18 MB, per instance, and XLA keeps several such temporaries). --knots, --sizes and --sequential
make it small.

Threads: OPENBLAS_NUM_THREADS=1 is set before numpy is imported, as in the other benchmarks,
so that numpy's BLAS does not compete with XLA; XLA's own CPU thread pool is left at its
default (all cores), which is where the batch can use the cores a single solve leaves idle.
The machine is shared: the load average at start and end are printed, and the ratios come from
the same run, so they share the load.

Usage: python benchmarks/batched.py [--knots N] [--sizes 1 8 32 64] [--sequential S]
       [--repeats R] [--seed 0] [--max-iterations M]
"""

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"  # before numpy is imported

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402

import jaxmm  # noqa: E402, F401  (enables float64)
from machine import format_time, log, machine_lines, render, timed  # noqa: E402
from jaxmm import batch, programs, solve, tasks  # noqa: E402
from jaxmm.solver import interior_point as ip  # noqa: E402

SCENARIO = "take_off"
PUBLISHED = tasks.SCENARIOS[SCENARIO]["knots"]
DEFAULT_SIZES = (1, 8, 32, 64)


def reduced_task(knots):
    """Take-off with N knots and the published 3.5–7 s horizon (Δt scaled by 70 / N)."""
    return tasks.scenario(SCENARIO, knots=knots, keep_horizon=True)


def statuses(codes):
    """"converged ×3, nan ×1" for status codes (an array or a list)."""
    names = [ip.Status(int(s)).name.lower() for s in np.atleast_1d(np.asarray(codes))]
    return ", ".join(f"{name} ×{names.count(name)}" for name in dict.fromkeys(names))


def run_batch(task, guesses, options, repeats):
    """(compile seconds, median solve seconds, batched TaskSolution)."""
    batched_task = batch.broadcast_task(task, batch.batch_size(guesses))
    compiled, compile_time = timed(lambda: programs.batch_solve.lower(batched_task, guesses, options).compile())
    times, result = [], None
    for _ in range(repeats):
        result, seconds = timed(lambda: jax.block_until_ready(compiled(batched_task, guesses)))
        times.append(seconds)
    return compile_time, statistics.median(times), result


def run_sequential(task, guesses, options):
    """(compile seconds, [solve seconds], [TaskSolution]) of the guesses one after another."""
    first = batch.instance(guesses, 0)
    compiled, compile_time = timed(lambda: programs.compile_solve(task, first, options))
    times, results = [], []
    for i in range(batch.batch_size(guesses)):
        guess = batch.instance(guesses, i)
        result, seconds = timed(lambda: jax.block_until_ready(compiled(guess)))
        log(f"  sequential {i + 1}: {format_time(seconds)}, {result.status.name.lower()}, "
            f"{int(result.solution.iterations)} iterations")
        times.append(seconds)
        results.append(result)
    return compile_time, times, results


def agreement(batched, singles):
    """(max relative objective difference, statuses equal, iterations equal) over the
    instances solved both ways."""
    worst, same_status, same_iterations = 0.0, True, True
    for i, single in enumerate(singles):
        mine = batch.instance(batched, i).solution
        a, b = float(mine.objective), float(single.solution.objective)
        if np.isfinite(a) and np.isfinite(b):
            worst = max(worst, abs(a - b) / max(abs(b), 1e-300))
        same_status &= int(mine.status) == int(single.solution.status)
        same_iterations &= int(mine.iterations) == int(single.solution.iterations)
    return worst, same_status, same_iterations


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--knots", type=int, default=PUBLISHED, help=f"N (default the published {PUBLISHED})")
    parser.add_argument("--sizes", type=int, nargs="+", default=list(DEFAULT_SIZES), help="batch sizes B")
    parser.add_argument("--sequential", type=int, default=None,
                        help="guesses solved one after another (default: the largest B)")  # fmt: skip
    parser.add_argument("--repeats", type=int, default=1, help="timed runs of each compiled batch (median reported)")
    parser.add_argument("--seed", type=int, default=0, help="seed of sample_guesses")
    parser.add_argument("--max-iterations", type=int, default=None, help="iteration limit of the solver")
    args = parser.parse_args()
    if min(args.sizes) < 1:
        parser.error("batch sizes must be ≥ 1")
    sequential = max(args.sizes) if args.sequential is None else args.sequential
    if not 1 <= sequential <= max(args.sizes):
        parser.error(f"--sequential must be between 1 and the largest batch size {max(args.sizes)}")
    options = solve.DEFAULT_OPTIONS
    if args.max_iterations is not None:
        options = dataclasses.replace(options, max_iterations=args.max_iterations)

    started = time.perf_counter()
    header = machine_lines(("jax", "jaxlib", "numpy"))
    task = reduced_task(args.knots)
    everything = batch.sample_guesses(task, jax.random.key(args.seed), max(args.sizes))
    first = lambda b: jax.tree.map(lambda leaf: leaf[:b], everything)  # noqa: E731

    log(f"{SCENARIO} N = {task.n_intervals}: {sequential} sequential solves...")
    single_compile, single_times, singles = run_sequential(task, first(sequential), options)
    one = statistics.median(single_times)

    rows, checks = [], []
    for size in args.sizes:
        log(f"B = {size}: compiling...")
        compile_time, solve_time, result = run_batch(task, first(size), options, args.repeats)
        log(f"B = {size}: solved in {format_time(solve_time)} (compile {format_time(compile_time)})")
        iterations = np.atleast_1d(np.asarray(result.solution.iterations))
        if size <= sequential:
            serial, mark = sum(single_times[:size]), ""
        else:
            serial, mark = size * one, "≈ "
        rows.append((
            size, format_time(compile_time), format_time(solve_time), format_time(solve_time / size),
            f"{int(iterations.max())} ({int(iterations.min())}–{int(iterations.max())})",
            f"{solve_time / one:.3g}×", mark + format_time(serial), f"{mark}{serial / solve_time:.3g}×", statuses(result.solution.status),
        ))  # fmt: skip
        log("  row: " + " | ".join(map(str, rows[-1])))  # in the log too, should a later batch be cut short
        solved_both = min(size, sequential)
        worst, same_status, same_iterations = agreement(result, singles[:solved_both])
        checks.append(f"B = {size}: first {solved_both} instances against the single solves: objective "
                      f"rel. difference ≤ {worst:.1e}, statuses {'equal' if same_status else 'DIFFER'}, "
                      f"iterations {'equal' if same_iterations else 'DIFFER'}")

    print("\n".join(header))
    print(f"{SCENARIO}, N = {task.n_intervals} (Δt {float(task.params.min_dt):.3g}–{float(task.params.max_dt):.3g} s), "
          f"{task.n_knots * task.layout.size + 1} variables; guesses: sample_guesses(seed {args.seed}), default scales; "
          f"solver tolerance {options.tolerance:g}, stationarity {options.stationarity:g}, max {options.max_iterations} "
          f"iterations; batch solve = median of {args.repeats} run(s); OPENBLAS_NUM_THREADS=1")
    print(f"sequential: {sequential} guesses one after another, compile {format_time(single_compile)} once, "
          f"total {format_time(sum(single_times))}, one solve (median) {format_time(one)} "
          f"(min {format_time(min(single_times))}, max {format_time(max(single_times))}); {statuses([r.solution.status for r in singles])}")
    print()
    print(render(("B", "compile", "batch solve", "per instance", "iterations: batch (instances)",
                  "batch / one solve", "sequential, same B guesses", "sequential / batch", "statuses"), rows))
    print()
    print("\n".join(checks))
    print()
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"Goal of the issue: B = 64 within 8× one solve. Total benchmark time {time.perf_counter() - started:.0f} s; "
          f"load average at the end {load}.")


if __name__ == "__main__":
    main()
