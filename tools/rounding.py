"""How much a solve's iteration count is owed to rounding: one scenario solved from its
published guess and from copies of it perturbed by a relative ``--scale`` (default 1e-12, far
below every tolerance), all by the same compiled program.

A perturbation that small changes nothing a user could see in the task, but the iterates part
ways after a few iterations (the line search's and the inertia correction's decisions are
thresholds), and the solve can end elsewhere after more or fewer iterations. A change to the
code that only reorders floating-point sums (a variable layout, a compiler flag) has the same
effect, so one solve's iteration count cannot tell such a change from a better or worse method:
this spread is the yardstick (take-off N = 70 took 243, 252 and 315 iterations with XLA's
fusion emitters on, off, and with the knot's variables in another order).

Printed: per copy (0: the published guess itself), the iterations, the factorisations per
iteration, the solve time, the objective, the status and ``analysis.validate``; then the
iterations' and solve times' median, minimum and maximum. Compile time apart. ``--option
name=value`` (repeatable) solves with ``solve.DEFAULT_OPTIONS`` so changed (a Python literal:
``--option regularisation_decrease=0.01``): compare a variant with the default by their spreads.
``--task name=value`` (repeatable) changes the task in the same way (a ``tasks.build_task``
keyword: ``--task boundary_tolerance=0.0``). Each answer's complementarity is printed beside it:
the largest product f_z c_z [N m] and the largest slack ε_n, ε_t. ``--elastic`` solves each
copy by ``solve.solve_elastic`` to exact complementarity (``--smooth-start``: with its smooth
start; implies ``--elastic``; ``--max-stages`` caps its raises of the slack weight): the
iterations column lists the stages, the spread counts their
sum, the objective is the published cost (eq. 32) of the answer, and ``validate`` checks it
against the task of its last stage.

Usage: python tools/rounding.py [--scenario take_off] [--knots N] [--copies 6]
       [--scale 1e-12] [--seed 0] [--option name=value ...] [--task name=value ...]
       [--elastic] [--smooth-start] [--max-stages 4]
"""

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"  # before numpy is imported

import pathlib  # noqa: E402
import sys  # noqa: E402

# benchmarks/machine.py: the machine, versions and tables that the benchmarks print too
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))

import argparse  # noqa: E402
import ast  # noqa: E402
import dataclasses  # noqa: E402
import statistics  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402

import jaxmm  # noqa: E402  (enables float64)
from machine import format_time, log, machine_lines, render, timed  # noqa: E402
from solve_scenarios import per_iteration  # noqa: E402
from jaxmm import analysis, programs, solve, tasks  # noqa: E402
from jaxmm.solver import interior_point as ip  # noqa: E402
from jaxmm.transcription import costs  # noqa: E402


def perturbed(guess, scale, seed):
    """``guess`` (a ``Trajectory``) with every knot entry x replaced by x (1 + scale · n), n a
    standard normal draw (``seed``); entries that are 0 stay 0, and T_total is kept."""
    rng = np.random.default_rng(seed)
    knots = jax.tree.map(lambda x: x * (1.0 + scale * rng.standard_normal(np.shape(x))), guess.knots)
    return type(guess)(knots=knots, total_time=guess.total_time)


def assignments(texts, fields, flag):
    """{name: value} from ``name=value`` strings (values: Python literals); a ValueError names an
    unknown name (not in ``fields``) or a value that is not a literal."""
    changes = {}
    for text in texts:
        name, sep, value = text.partition("=")
        if not sep or name.strip() not in fields:
            raise ValueError(f"{flag} {text!r}: expected name=value with name one of {', '.join(sorted(fields))}")
        try:
            changes[name.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            raise ValueError(f"{flag} {text!r}: {value.strip()!r} is not a Python literal") from None
    return changes


def solver_options(texts):
    """``solve.DEFAULT_OPTIONS`` with the ``name=value`` strings applied."""
    fields = {f.name for f in dataclasses.fields(ip.Options)}
    return dataclasses.replace(solve.DEFAULT_OPTIONS, **assignments(texts, fields, "--option"))


def task_overrides(texts):
    """``tasks.build_task`` keywords from the ``name=value`` strings."""
    return assignments(texts, set(tasks.build_task.__kwdefaults__), "--task")


def complementarity(trajectory):
    """(the largest f_z c_z [N m], the largest slack ε_n or ε_t) of a trajectory."""
    knots = trajectory.knots
    product = np.asarray(knots.contact_forces[..., 2]) * np.asarray(knots.contact_points[..., 2])
    slack = max(float(np.max(knots.normal_slack, initial=0.0)), float(np.max(knots.tangential_slack, initial=0.0)))
    return float(np.max(product, initial=0.0)), slack


def plain_run(task, compiled):
    """guess → (TaskSolution, task, (iterations,)) by the compiled solve."""

    def plain(guess):
        result = compiled(guess)
        return result, task, (int(result.solution.iterations),)

    return plain


def elastic_run(task, options, smooth_start, max_stages):
    """guess → (TaskSolution, the task it solved, iterations per stage) by ``solve_elastic``."""

    def elastic(guess):
        answer = solve.solve_elastic(task, guess, options, smooth_start=smooth_start, max_stages=max_stages)
        return answer.result, answer.task, answer.iterations

    return elastic


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="take_off", choices=tuple(tasks.SCENARIOS))
    parser.add_argument("--knots", type=int, default=None, help="N (default: the published one)")
    parser.add_argument("--copies", type=int, default=6, help="perturbed copies of the guess, beside the guess itself")
    parser.add_argument("--scale", type=float, default=1e-12, help="relative size of the perturbation")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first copy (copy i: seed + i − 1)")
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                        help="a solver option changed from the default (repeatable)")
    parser.add_argument("--task", action="append", default=[], metavar="NAME=VALUE",
                        help="a build_task keyword changed from the scenario's (repeatable)")
    parser.add_argument("--elastic", action="store_true", help="solve by solve_elastic, to exact complementarity")
    parser.add_argument("--smooth-start", action="store_true",
                        help="solve_elastic with its smooth start (the squared slack penalty first)")
    parser.add_argument("--max-stages", type=int, default=4, help="solve_elastic's raises of the slack weight")
    args = parser.parse_args()
    if args.copies < 0 or not args.scale > 0:
        parser.error("--copies must be ≥ 0 and --scale > 0")
    try:
        options = solver_options(args.option)
        overrides = task_overrides(args.task)
    except (ValueError, TypeError) as error:
        parser.error(str(error))
    print("\n".join(machine_lines(["jax", "jaxlib", "numpy"])))
    task = tasks.scenario(args.scenario, knots=args.knots, **overrides)
    guess = tasks.initial_guess(task)
    log(f"{args.scenario} N = {task.n_intervals}: compiling...")
    compiled, compile_time = timed(lambda: programs.compile_solve(task, guess, options))
    elastic = args.elastic or args.smooth_start
    run = elastic_run(task, options, args.smooth_start, args.max_stages) if elastic else plain_run(task, compiled)
    smooth = ", smooth start" if args.smooth_start else ""
    mode = [f"solve_elastic (≤ {args.max_stages} raises{smooth})"] if elastic else []
    changed = ", ".join(args.option + args.task + mode) or "the default options and task"
    print(f"\n{args.scenario}, N = {task.n_intervals}, {changed}: compile {format_time(compile_time)}; "
          f"copies perturbed by a relative {args.scale:g} (seeds {args.seed}..{args.seed + args.copies - 1})\n")
    rows, iterations, times = [], [], []
    for copy in range(args.copies + 1):
        start = guess if copy == 0 else perturbed(guess, args.scale, args.seed + copy - 1)
        (result, solved_task, stages), seconds = timed(lambda: jax.block_until_ready(run(start)))
        report = analysis.validate(solved_task, result.trajectory)
        n = sum(stages)
        iterations.append(n)
        times.append(seconds)
        product, slack = complementarity(result.trajectory)
        rows.append((copy, " + ".join(map(str, stages)), f"{per_iteration(result.solution, 'factorisations'):.2f}",
                     format_time(seconds), f"{float(costs.total_cost(task, result.trajectory)):.7g}",
                     result.status.name.lower(),
                     f"{product:.1e}", f"{slack:.1e}",
                     "ok" if report.ok else f"FAILED ({', '.join(report.failed)})"))
        log(f"copy {copy}: {n} iterations, {format_time(seconds)}, {result.status.name.lower()}")
    print(render(("copy", "iterations", "factorisations / it.", "solve", "objective", "status",
                  "max f_z c_z", "max ε", "validate"), rows))
    print()
    print(render(("", "median", "min", "max"), [
        ("iterations", statistics.median(iterations), min(iterations), max(iterations)),
        ("solve", format_time(statistics.median(times)), format_time(min(times)), format_time(max(times))),
    ]))


if __name__ == "__main__":
    main()
