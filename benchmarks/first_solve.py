"""Time to a first answer: a scenario solved as a user's first and second process would solve it.

Two fresh processes solve the same scenario (``tasks.scenario(name)`` at its published N, or
--knots) from its published guess with the default options, each with
``compilation.use_persistent_cache`` pointed at the same new directory:

* first, with the cache empty: building the task, compiling the solve's three programs
  (``programs.compile_solve``: start, advance, finish), and solving;
* second, with the cache the first one filled: the same, the programs now loaded from the
  executable store.

Each prints the time to build the task, to compile (or load) the programs and to solve, the
iterations, status, objective and ``jaxmm.validate``'s verdict; the table says which backend and
devices ran it. Nothing is pinned: a user's process has every core of the machine.

Usage: python benchmarks/first_solve.py [--scenarios take_off] [--knots N]
"""

import argparse
import os
import tempfile

from machine import format_time, log, machine_lines, probe, render

PROBE = r'''
import json, sys, time
t0 = time.perf_counter()
import jax
import jaxmm
from jaxmm import compilation, programs, tasks
name, knots, cache = sys.argv[1:4]
compilation.use_persistent_cache(cache)
t1 = time.perf_counter()
task = tasks.scenario(name) if knots == "0" else tasks.scenario(name, knots=int(knots))
t2 = time.perf_counter()
run = programs.compile_solve(task)
t3 = time.perf_counter()
result = run()
jax.block_until_ready(result)
t4 = time.perf_counter()
report = jaxmm.validate(task, result.trajectory)
print("PROBE " + json.dumps(dict(
    backend=jax.default_backend(), devices=len(jax.devices()), device=jax.devices()[0].device_kind,
    knots=task.n_intervals, imports=t1 - t0, task=t2 - t1, compile=t3 - t2, solve=t4 - t3,
    iterations=int(result.solution.iterations), status=result.status.name,
    objective=float(result.solution.objective), valid=bool(report.ok))))
'''


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", default="take_off")
    parser.add_argument("--knots", type=int, default=0, help="knot intervals of every scenario (default: published)")
    args = parser.parse_args()
    rows = []
    for name in [s for s in args.scenarios.split(",") if s]:
        with tempfile.TemporaryDirectory(prefix="jaxmm-first-solve-") as cache:
            for label in ("first process (compiles)", "second process (loads)"):
                log(f"{name}: {label}")
                r = probe(PROBE, (name, args.knots, cache), f"the probe of {name}")
                rows.append((name, r["knots"], label, f"{r['backend']} × {r['devices']} ({r['device']})",
                             format_time(r["task"]), format_time(r["compile"]), format_time(r["solve"]),
                             f"{r['iterations']}, {r['status']}", f"{r['objective']:.6e}",
                             "ok" if r["valid"] else "FAILED"))
    print("\n".join(machine_lines(["jax", "jaxlib"])))
    print(f"XLA_FLAGS: {os.environ.get('XLA_FLAGS', '(unset: XLA defaults)')}\n")
    header = ("scenario", "N", "process", "backend", "task", "compile or load", "solve", "iterations, status",
              "objective", "validate")
    print(render(header, rows))


if __name__ == "__main__":
    main()
