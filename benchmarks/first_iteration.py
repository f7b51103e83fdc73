"""The take-off N = 70 iteration program compiled, then loaded, on whatever backend JAX has: the
check run on a lent GPU.

Two fresh processes with ``compilation.use_persistent_cache`` on the same new directory: the
first compiles ``programs.start`` and ``programs.advance`` (``advance.compiled``), the second
loads them from the executable store. Each reports the time to build the task, to start (compile
or load ``start``, and run it), to compile or load ``advance``, from the start to the end of the
first iteration, and the time per iteration (median of three runs of iterations 20–30); the
second then solves the task with ``jaxmm.solve_task`` (its iterations, status and objective).

Usage: python benchmarks/first_iteration.py [--scenario take_off]
"""

import argparse
import tempfile

from machine import format_time, log, machine_lines, probe, render

PROBE = r'''
import json, sys, time
import jax, numpy as np
import jaxmm
from jaxmm import compilation, programs, tasks
from jaxmm.solver import interior_point as ip
mode, name, cache = sys.argv[1:4]
compilation.use_persistent_cache(cache, min_compile_seconds=0.0)
out = dict(backend=jax.default_backend(), device=jax.devices()[0].device_kind)
t0 = time.perf_counter()
task = tasks.scenario(name)
guess, started, m, b = programs.prepare(task, tasks.initial_guess(task), programs.DEFAULT_OPTIONS)
options = ip.iteration_options(started)
out["task"] = time.perf_counter() - t0
t1 = time.perf_counter()
state = jax.block_until_ready(programs.start(task, guess, started, m, b))
out["start"] = time.perf_counter() - t1
t2 = time.perf_counter()
program = programs.advance.compiled(task, state, options, 1)
out["advance"] = time.perf_counter() - t2
first = jax.block_until_ready(program(task, state, options, 1))
out["first_iteration"] = time.perf_counter() - t1
at = jax.block_until_ready(program(task, first, options, 20))
times = []
for _ in range(3):
    t = time.perf_counter()
    after = jax.block_until_ready(program(task, at, options, 30))
    times.append(time.perf_counter() - t)
out["per_iteration"] = float(np.median(times)) / (int(after.iterations) - int(at.iterations))
if mode == "hit":
    t = time.perf_counter()
    result = jax.block_until_ready(jaxmm.solve_task(task))
    out.update(solve=time.perf_counter() - t, status=result.status.name, iterations=int(result.solution.iterations),
               objective=float(result.solution.objective))
print("PROBE " + json.dumps(out), flush=True)
'''


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="take_off")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="jaxmm-first-iteration-") as cache:
        for mode, label in (("cold", "compiles"), ("hit", "loads")):
            log(f"{args.scenario}: {label}")
            r = probe(PROBE, (mode, args.scenario, cache), f"the {mode} probe of {args.scenario}")
            solve = (f"{r['iterations']}, {r['status']}, {format_time(r['solve'])}, {r['objective']:.6e}"
                     if mode == "hit" else "–")
            rows.append((label, f"{r['backend']} ({r['device']})", format_time(r["task"]), format_time(r["start"]),
                         format_time(r["advance"]), format_time(r["first_iteration"]),
                         format_time(r["per_iteration"]), solve))
    print("\n".join(machine_lines(["jax", "jaxlib"])) + "\n")
    header = ("process", "backend", "task", "start", "advance compile or load", "start → first iteration",
              "per iteration", "solve_task: iterations, status, time, objective")
    print(render(header, rows))


if __name__ == "__main__":
    main()
