"""How long a solve takes to compile, and how large its compiled iteration is, per scenario;
with --compare REV, the same for another commit in the same run, side by side.

For each scenario (``tasks.scenario(name)`` on the default assembled iRonCub at its published N,
or --knots) and each revision, two fresh processes pinned to one core measure the iterations
program every solve runs (``programs.advance``, options ``programs.DEFAULT_OPTIONS``):

* cold, with an empty persistent compilation cache: the first call of ``programs.start`` (the
  state before the first iteration: tracing, compiling and running it), the time to trace and
  lower the iterations program
  (``.trace(...).lower()``), XLA's compile time (``.compile()``), the size of the compiled
  program (``compilation.program_size``: HLO instructions in its optimised text, and kernels,
  the instructions outside fusion bodies that run as an operation of their own; a second table
  gives the kernels per source file, ``compilation.kernel_sources``), the Cholesky
  factorisations and triangular solves (LAPACK custom calls) in the lowered program with every
  call inlined (``compilation.custom_calls``), and the time per iteration (median of
  --repeats runs of iterations --skip to --skip + --iterations from the published guess);
* warm, a second process with the cache the first one filled: the wall time from the first
  call of the solve's programs (``programs.start``, then ``programs.advance`` for one iteration)
  to the end of that first iteration: tracing, lowering, loading from the cache, one iteration.

--codegen adds a third process per revision that compiles the iterations program under XLA's
per-kernel timers (``compilation.CODEGEN_TIMERS``) and prints the code-generation seconds per
source file (``compilation.codegen_seconds``): where the compile time goes, which kernel counts
do not say (identical fusions are compiled once, copies not at all).

--compare REV checks REV out into a temporary git worktree and runs the same two processes with
that worktree's ``jaxmm`` (REV needs ``jaxmm.programs``, whose ``start``/``advance`` these calls
use). XLA runs with its default optimisation flags unless $XLA_FLAGS says otherwise (the header
prints it).

Usage: python benchmarks/compile.py [--scenarios take_off,jumping,walk_to_fly,take_off_and_landing]
       [--knots N] [--compare REV] [--skip 20] [--iterations 10] [--repeats 3] [--codegen]
"""

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile

from machine import format_time, log, machine_lines, render

from jaxmm import compilation  # the size of a program from its text (this tree's, for every revision)

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENARIOS = ("take_off", "jumping", "walk_to_fly", "take_off_and_landing")

# The measurement, run in a fresh process with the revision's jaxmm first on sys.path; prints one
# JSON line. Kept to the calls every revision with ``jaxmm.programs`` has.
PROBE = r'''
import json, pathlib, sys, time
t_import = time.perf_counter()
mode, name, knots, skip, iterations, repeats, cache, texts = sys.argv[1:9]
import jax, numpy as np
import jaxmm
from jaxmm import compilation, programs, tasks
from jaxmm.solver import interior_point as ip
compilation.use_persistent_cache(cache, min_compile_seconds=0.0)
task = tasks.scenario(name) if knots == "0" else tasks.scenario(name, knots=int(knots))
guess, started, m, b = programs.prepare(task, tasks.initial_guess(task), programs.DEFAULT_OPTIONS)
options = ip.iteration_options(started)  # what solve_task iterates with
out = dict(knots=task.n_knots)

if mode == "codegen":  # XLA's per-kernel timers (stderr) of the iterations program's compile alone
    lowered = programs.advance.trace(task, programs.start(task, guess, started, m, b), options, int(skip)).lower()
    sys.stderr.flush()
    begin = pathlib.Path(texts, "codegen.log").stat().st_size
    compiled = lowered.compile()
    sys.stderr.flush()
    pathlib.Path(texts, "compiled.txt").write_text(compiled.as_text())
    out.update(log_begin=begin)
elif mode == "cold":
    t0 = time.perf_counter()
    state = jax.block_until_ready(programs.start(task, guess, started, m, b))
    out.update(start=time.perf_counter() - t0)
    t0 = time.perf_counter()
    lowered = programs.advance.trace(task, state, options, int(skip)).lower()
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    pathlib.Path(texts, "lowered.txt").write_text(lowered.as_text())
    pathlib.Path(texts, "compiled.txt").write_text(compiled.as_text())
    out.update(trace_lower=t1 - t0, compile=t2 - t1)
    at = jax.block_until_ready(compiled(task, state, int(skip)))
    times = []
    for _ in range(int(repeats)):
        t = time.perf_counter()
        after = jax.block_until_ready(compiled(task, at, int(skip) + int(iterations)))
        times.append(time.perf_counter() - t)
    done = int(after.iterations) - int(at.iterations)
    out.update(per_iteration=float(np.median(times)) / max(done, 1), iterations=done)
    # The calls a solve makes, so that whatever a revision keeps on disk besides JAX's cache
    # (jaxmm's executable store) is there for the warm probe.
    jax.block_until_ready(programs.advance(task, programs.start(task, guess, started, m, b), options, 1))
else:
    t0 = time.perf_counter()
    state = programs.start(task, guess, started, m, b)
    first = jax.block_until_ready(programs.advance(task, state, options, 1))
    out.update(first_iteration=time.perf_counter() - t0, import_seconds=t_import)
print("PROBE " + json.dumps(out))
'''


def probe(source, mode, name, args, cache, texts):
    """Run PROBE with the jaxmm of ``source`` (a directory) on one core; returns its JSON (the
    cold probe leaves the program's lowered and compiled texts in the directory ``texts``)."""
    path = os.pathsep.join(p for p in (str(source), os.environ.get("PYTHONPATH", "")) if p)
    environment = dict(os.environ, PYTHONPATH=path, OPENBLAS_NUM_THREADS="1")
    command = ["taskset", "-c", "0", sys.executable, "-c", PROBE, mode, name, str(args.knots or 0), str(args.skip),
               str(args.iterations), str(args.repeats), str(cache), str(texts)]
    if mode == "codegen":
        environment.update(compilation.CODEGEN_TIMERS)
        with open(pathlib.Path(texts, "codegen.log"), "w") as log:
            result = subprocess.run(command, env=environment, stdout=subprocess.PIPE, stderr=log, text=True, cwd=source)
        result.stderr = pathlib.Path(texts, "codegen.log").read_text(errors="replace")
    else:
        result = subprocess.run(command, env=environment, capture_output=True, text=True, cwd=source)
    lines = [line for line in result.stdout.splitlines() if line.startswith("PROBE ")]
    if result.returncode or not lines:
        raise RuntimeError(f"the {mode} probe of {name} at {source} failed:\n{result.stderr[-3000:]}")
    return json.loads(lines[-1][len("PROBE "):])


def measure(source, label, name, args):
    """Both probes of one scenario for one revision: a row of the table."""
    with tempfile.TemporaryDirectory(prefix="jaxmm-compile-cache-") as cache, \
            tempfile.TemporaryDirectory(prefix="jaxmm-compile-texts-") as texts:
        log(f"{label} {name}: cold")
        cold = probe(source, "cold", name, args, cache, texts)
        log(f"{label} {name}: cache hit")
        warm = probe(source, "warm", name, args, cache, texts)
        calls = compilation.custom_calls(pathlib.Path(texts, "lowered.txt").read_text())
        compiled = pathlib.Path(texts, "compiled.txt").read_text()
        size, sources = compilation.program_size(compiled), compilation.kernel_sources(compiled)
        codegen = {}
        if args.codegen:
            log(f"{label} {name}: code generation timers")
            begin = probe(source, "codegen", name, args, pathlib.Path(texts, "cache"), texts)["log_begin"]
            codegen = compilation.codegen_seconds(pathlib.Path(texts, "codegen.log").read_text(errors="replace")[begin:],
                                                  pathlib.Path(texts, "compiled.txt").read_text())
    return dict(cold, **warm, hlo=size, sources=sources, codegen=codegen, cholesky=calls.get("lapack_dpotrf_ffi", 0),
                triangular=calls.get("lapack_dtrsm_ffi", 0))


def revision(rev):
    """The commit hash of ``rev`` in this repository."""
    return subprocess.run(["git", "rev-parse", "--short", rev], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", default=",".join(SCENARIOS))
    parser.add_argument("--knots", type=int, default=None, help="knot count of every scenario (default: published)")
    parser.add_argument("--compare", default=None, metavar="REV", help="another commit, measured in the same run")
    parser.add_argument("--skip", type=int, default=20)
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--codegen", action="store_true",
                        help="a third process per revision: XLA's code-generation seconds per source file")
    args = parser.parse_args()
    names = [s for s in args.scenarios.split(",") if s]
    unknown = sorted(set(names) - set(SCENARIOS))
    if unknown:
        parser.error(f"unknown scenarios {unknown}; known: {', '.join(SCENARIOS)}")
    dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                           text=True).stdout.strip()
    sources = [(f"{revision('HEAD')}{' + changes' if dirty else ''}", ROOT)]
    with tempfile.TemporaryDirectory(prefix="jaxmm-compare-") as scratch:
        if args.compare:
            other = pathlib.Path(scratch) / "tree"
            subprocess.run(["git", "worktree", "add", "--detach", str(other), args.compare], cwd=ROOT, check=True,
                           capture_output=True)
            sources.append((revision(args.compare), other))
        try:
            rows, by_source = [], []
            for name in names:
                results = [(label, measure(source, label, name, args)) for label, source in sources]
                by_source.append((name, results))
                base = results[-1][1]
                for label, r in results:
                    ratio = lambda key: f" ({r[key] / base[key]:.2f}×)" if len(results) > 1 else ""  # noqa: E731
                    rows.append((name, r["knots"], label, format_time(r["start"]) + ratio("start"),
                                 format_time(r["trace_lower"]) + ratio("trace_lower"),
                                 format_time(r["compile"]) + ratio("compile"), f"{r['hlo'][0]:,}", f"{r['hlo'][1]:,}",
                                 f"{r['cholesky']} / {r['triangular']}",
                                 format_time(r["first_iteration"]) + ratio("first_iteration"),
                                 format_time(r["per_iteration"]) + ratio("per_iteration")))
        finally:
            if args.compare:
                subprocess.run(["git", "worktree", "remove", "--force", str(other)], cwd=ROOT, capture_output=True)
    print("\n".join(machine_lines(["jax", "jaxlib"])))
    print(f"XLA_FLAGS: {os.environ.get('XLA_FLAGS', '(unset: XLA defaults)')}; one core per process; iterations "
          f"{args.skip}–{args.skip + args.iterations} for the time per iteration, median of {args.repeats}\n")
    header = ("scenario", "N", "revision", "start, first call", "trace + lower", "XLA compile", "HLO instructions", "kernels",
              "Cholesky / triangular solves", "cache hit → first iteration", "per iteration")
    print(render(header, rows))
    if len(sources) > 1:
        print(f"\nRatios: {sources[0][0]} / {sources[1][0]}.")
    for name, results in by_source:
        per_source(f"{name}: kernels by the source file of their innermost line (compilation.kernel_sources)",
                   results, "sources", lambda v: f"{v:,}")
        if args.codegen:
            per_source(f"{name}: XLA's code-generation seconds by source file, one core (compilation.codegen_seconds)",
                       results, "codegen", lambda v: f"{v:.2f}")


def per_source(title, results, key, fmt):
    """Print a table of results[...][key] ({source file: value}) per revision, largest first."""
    print(f"\n{title}\n")
    files = sorted({f for _, r in results for f in r[key]}, key=lambda f: -results[0][1][key].get(f, 0))
    print(render(("source",) + tuple(label for label, _ in results),
                 [(f,) + tuple(fmt(r[key].get(f, 0)) for _, r in results) for f in files]))


if __name__ == "__main__":
    main()
