"""Where the time of a solver iteration goes: a profile of the compiled iterations of one
scenario, each XLA operation's time attributed to the jaxmm function that emitted it.

How: the solve's iterations program (``programs.advance``, the one every solve runs) is
compiled once; it runs ``--skip`` iterations from the published guess, then ``--iterations``
more from that point, twice plainly (the faster gives the wall time per iteration) and once
under ``jax.profiler`` (the profiler's own events slow it; the plain time is the true one). Every
XLA operation the trace shows (a fusion, a dot, a copy …) is looked up in the compiled
program's text, whose metadata keep the Python stack that traced it, and its time goes:

* to its innermost jaxmm module (the table by module: additive, it sums to the time spent
  inside operations);
* to every jaxmm function on its stack (the table by function: inclusive, a function's time
  includes that of the functions it calls, so it does not sum to anything; the operations are
  counted the same way).

Operations the program's text gives no stack for (XLA's own copies, some products) are
"unattributed", and listed apart with their result shapes and opcodes; the time between
operations (launching them, the loops' control) is reported apart. The attribution reads the
stack tables of the compiled program's text (``FileNames``, ``FunctionNames``,
``FileLocations``, ``StackFrames``, ``stack_frame_id=``), as jaxlib 0.10 prints them; a jaxlib
that prints none makes the script stop with a message saying so.

``--option name=value`` changes a solver option (as ``tools/rounding.py`` reads it), so that a
variant's iteration is profiled beside the default's.

Usage: python tools/profile_iteration.py [--scenario take_off] [--knots N] [--skip 20]
       [--iterations 10] [--top 40] [--unattributed 15] [--cache DIR] [--option name=value ...]
"""

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"  # before numpy is imported

import pathlib  # noqa: E402
import sys  # noqa: E402

# benchmarks/machine.py: the machine, versions and tables that the benchmarks print too; and
# tools/rounding.py's reading of --option
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

import argparse  # noqa: E402
import collections  # noqa: E402
import dataclasses  # noqa: E402
import re  # noqa: E402
import tempfile  # noqa: E402

import jax  # noqa: E402

import jaxmm  # noqa: E402,F401  (enables float64)
from machine import format_time, log, machine_lines, render, timed  # noqa: E402
from rounding import solver_options  # noqa: E402
from jaxmm import compilation, programs, tasks  # noqa: E402
from jaxmm.solver import interior_point as ip  # noqa: E402

# Events of the trace that are not operations of the program: the executor's and the thread
# pool's own spans, the end marks of operations, and the control operations that contain others.
CONTAINERS = ("end:", "ThunkExecutor", "ThreadpoolListener", "while", "cond", "call")
TABLES = ("FileNames", "FunctionNames", "FileLocations", "StackFrames")


def instruction_signatures(text):
    """{instruction name: "its result shape and opcode"} from a compiled program's text (say
    ``f64[71,178,178]{2,1,0} copy``): what an operation without a stack was."""
    found = (re.match(r"\s*(?:ROOT )?%([\w.\-]+) = (\S+) ([\w\-]+)\(", line) for line in text.splitlines())
    return {m[1]: f"{m[2]} {m[3]}" for m in found if m}


def stack_tables(text):
    """{instruction name: its Python stack, outermost first, as (file, function) pairs} from a
    compiled program's text."""
    tables = {name: {} for name in TABLES}
    table = None
    instructions = {}
    for line in text.splitlines():
        stripped = line.strip()
        if stripped in TABLES:
            table = stripped
            continue
        entry = re.match(r"(\d+) (.*)$", stripped) if table else None
        if entry is None:
            table = None
            found = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = .*stack_frame_id=(\d+)", line)
            if found:
                instructions[found[1]] = int(found[2])
            continue
        key, value = int(entry[1]), entry[2]
        if table in ("FileNames", "FunctionNames"):
            tables[table][key] = value.strip('"')
        elif table == "FileLocations":
            ids = re.match(r"\{file_name_id=(\d+) function_name_id=(\d+)", value)
            tables[table][key] = (tables["FileNames"][int(ids[1])], tables["FunctionNames"][int(ids[2])])
        else:
            ids = re.match(r"\{file_location_id=(\d+)(?: parent_frame_id=(\d+))?", value)
            tables[table][key] = (int(ids[1]), int(ids[2] or 0))
    if not instructions or not tables["StackFrames"]:
        sys.exit("the compiled program's text holds no stack tables (FileNames … StackFrames, stack_frame_id=): "
                 "this jaxlib prints its metadata otherwise, and the profile cannot be attributed")

    def stack(frame):
        out, seen = [], set()
        while frame and frame not in seen:
            seen.add(frame)
            location, parent = tables["StackFrames"][frame]
            out.append(tables["FileLocations"][location])
            frame = parent
        return out[::-1]

    return {name: stack(frame) for name, frame in instructions.items()}


def operation_times(trace_directory):
    """({operation name: total ns}, {operation name: count}, the span of the traced run [ns], the
    time during which some operation ran [ns]) from the trace ``jax.profiler`` wrote."""
    files = sorted(pathlib.Path(trace_directory).rglob("*.xplane.pb"))
    if not files:
        sys.exit(f"jax.profiler wrote no trace under {trace_directory}")
    profile = jax.profiler.ProfileData.from_file(str(files[-1]))
    # XLA's threads each have a line of events; their operations are merged on one time axis.
    events = sorted((e.start_ns, e.end_ns, e.name) for plane in profile.planes for line in plane.lines
                    if line.name.startswith("tf_XLA") for e in line.events)
    times, counts = collections.Counter(), collections.Counter()
    span = max(end for _, end, _ in events) - events[0][0] if events else 0
    inside, merged = 0, None
    for start, end, name in events:
        if name.startswith(CONTAINERS):
            continue
        times[name] += end - start
        counts[name] += 1
        if merged is None or start > merged[1]:
            inside += 0 if merged is None else merged[1] - merged[0]
            merged = [start, end]
        else:
            merged[1] = max(merged[1], end)
    inside += 0 if merged is None else merged[1] - merged[0]
    return times, counts, span, inside


def jaxmm_frames(stack):
    """The jaxmm (module, function) pairs of a stack, outermost first, each once."""
    out = []
    for file, function in stack:
        if "/jaxmm/" in file:
            entry = (file.split("/jaxmm/", 1)[1], function)
            if entry not in out:
                out.append(entry)
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="take_off")
    parser.add_argument("--knots", type=int, default=None, help="N (default: the published one)")
    parser.add_argument("--skip", type=int, default=20, help="iterations run before the profiled ones")
    parser.add_argument("--iterations", type=int, default=10, help="iterations profiled")
    parser.add_argument("--top", type=int, default=40, help="rows of the table by function")
    parser.add_argument("--cache", default=None, help="a persistent compilation cache directory")
    parser.add_argument("--unattributed", type=int, default=15, help="rows of the table of unattributed operations")
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                        help="a solver option changed from the default (repeatable)")
    args = parser.parse_args()
    if args.skip < 0 or args.iterations < 1:
        parser.error("--skip must be ≥ 0 and --iterations ≥ 1")
    if args.cache:
        compilation.use_persistent_cache(args.cache)

    for line in machine_lines(("jax", "jaxlib")):
        print(line)
    task = tasks.scenario(args.scenario, knots=args.knots, keep_horizon=args.knots is not None)
    try:
        options = dataclasses.replace(solver_options(args.option), max_iterations=args.skip + args.iterations)
    except ValueError as error:
        parser.error(str(error))
    guess, options, multipliers, bound_multipliers = programs.prepare(task, None, options)
    state = programs.start(task, guess, options, multipliers, bound_multipliers)
    options = ip.iteration_options(options)
    log("compiling the iterations …")
    advance, compile_time = timed(lambda: programs.advance.lower(task, state, options, options.max_iterations).compile())
    text = advance.as_text()
    origins, signatures = stack_tables(text), instruction_signatures(text)
    start = jax.block_until_ready(advance(task, state, args.skip))
    if int(start.status) != int(ip.Status.RUNNING):
        sys.exit(f"the solve stopped ({ip.Status(int(start.status)).name}) within the first {args.skip} iterations")
    until = args.skip + args.iterations
    plain = min(timed(lambda: jax.block_until_ready(advance(task, start, until)))[1] for _ in range(2))
    with tempfile.TemporaryDirectory() as directory:
        jax.profiler.start_trace(directory)
        end = jax.block_until_ready(advance(task, start, until))
        jax.profiler.stop_trace()
        times, counts, span, inside = operation_times(directory)
    done = int(end.iterations) - args.skip
    if done < 1:
        sys.exit("no iteration ran in the profiled slice")

    per = lambda ns: format_time(ns / 1e9 / done)  # noqa: E731
    changed = f", {', '.join(args.option)}" if args.option else ""
    print(f"\n{args.scenario}, N = {task.n_intervals}{changed}: iterations {args.skip + 1}–{args.skip + done} "
          f"(compile {compile_time:.1f} s)")
    print(f"per iteration: {format_time(plain / done)} plain; {per(span)} profiled, of which {per(inside)} "
          f"inside {sum(counts.values()) / done:.0f} operations and {per(span - inside)} between them")
    by_module, by_function, operations = collections.Counter(), collections.Counter(), collections.Counter()
    unattributed = collections.Counter()
    for name, ns in times.items():
        frames = jaxmm_frames(origins.get(name, ()))
        by_module[frames[-1][0] if frames else "(unattributed)"] += ns
        if not frames:
            unattributed[name] += ns
        for module, function in frames:
            by_function[f"{module}:{function}"] += ns
            operations[f"{module}:{function}"] += counts[name]
    total = sum(times.values())
    print("\nBy module (each operation's innermost jaxmm module; sums to the time inside operations):\n")
    print(render(("module", "per iteration", "share"),
                 [(m, per(ns), f"{100 * ns / total:.1f} %") for m, ns in by_module.most_common()]))
    print("\nBy function (inclusive: a function's operations include its callees'):\n")
    print(render(("function", "per iteration", "operations / it."),
                 [(f, per(ns), f"{operations[f] / done:.0f}") for f, ns in by_function.most_common(args.top)]))
    print("\nThe unattributed operations, longest first (result shape and opcode from the program's text):\n")
    print(render(("operation", "what", "per iteration", "runs / it."),
                 [(name, signatures.get(name, "?"), per(ns), f"{counts[name] / done:.0f}")
                  for name, ns in unattributed.most_common(args.unattributed)]))


if __name__ == "__main__":
    main()
