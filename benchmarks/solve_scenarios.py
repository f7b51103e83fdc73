"""Solve the four published scenarios with the JAX interior-point solver
(``jaxmm.solve.solve_task``) from the published initial guess, and optionally with the IPOPT
reference (``jaxmm.reference.solve_ipopt``) from the same guess, in the same run.

Each scenario is ``tasks.scenario(name)`` on the default assembled iRonCub, at its published N
(take-off 70, take-off and landing 200, walk to fly 100, jumping 60) unless --knots-override is
given, started from ``tasks.initial_guess``. The complementarity slacks are penalised linearly,
as in the published runs; --slack-penalty squared solves the paper's text's variant instead.

What is measured (wall clock):

* ours: compile time = ``jaxmm.programs.compile_solve(task, guess, options)``
  (tracing, lowering and XLA compilation of the solve's three programs: start, the iterations
  in one ``lax.while_loop``, finish); solve time = median over --repeats runs of them
  (``jax.block_until_ready``); they are compiled ahead of time, so there is no warm-up call. Also: the problem size (variables =
  (N + 1) knots × knot size + T_total; equality and inequality rows from the shapes of
  ``stagewise.residuals``, each inequality row two-sided with its own bounds, variable boxes
  not counted), the barrier updates and Newton iterations, the mean block solves per iteration
  (the solver history's ``linear_solves``: refinements, second-order corrections) and
  factorisations per iteration (its ``factorisations``: the inertia correction's attempts, a
  failed one counted up to its first indefinite block), the status, and
  ``jaxmm.analysis.validate`` of the trajectory (its table is printed after the main table).
  The default solver tolerance is 1e-6 on the violation (``solve.DEFAULT_OPTIONS``).
* --ipopt: ``solve_ipopt(task, urdf, guess, tol=1e-4)`` (the paper's tolerance, physical units;
  exact Hessian, MUMPS) on the same robot, read from ``jaxmm.assemble_urdf`` written to a
  temporary file; one call (no repeats): build time (``ReferenceNLP`` construction, ADAM
  kinematics), setup time (the ``nlpsol`` construction), IPOPT's own wall time, iterations and
  status, and the speed-ups IPOPT solve / our solve, IPOPT solve / (our compile + solve) and
  (IPOPT build + setup + solve) / (our compile + solve). WARNING: IPOPT is slow: take-off at
  N = 70 takes about 10 minutes on the 2-core benchmark machine, the longer scenarios more.
* For both sides, the objective and the max constraint violation of the returned trajectory are
  evaluated by the same jitted JAX function: ``stagewise.residuals(nlp, Z, θ).cost`` and
  ``interior_point.violation(nlp, Z, θ)[0]`` (the NLP's units: every constraint group and
  the variable boxes) after ``transcription.to_variables(task, trajectory)``.
* --knots: time per iteration against N on take-off (default N = 60, 100, 200, 400): each N
  compiled (compile time reported) and solved with a budget of 10 iterations (or
  --max-iterations); (solve time / iterations) and that divided by N, which is constant if
  the cost of an iteration grows linearly with N. The per-iteration time includes the
  once-per-solve setup (first cost gradient, initial violation) and varies with the number of
  line-search trials. Given alone, --knots skips the scenario table; add --scenarios for both.

--coarse NC solves each scenario coarse to fine: the scenario on NC intervals over the same
horizons (``tasks.with_intervals``) from its published guess, then the scenario itself from that
answer resampled to its knots; IPOPT still starts from the published guess. The iterations
column then reads "coarse + fine"; compile and solve times count both levels.

--elastic solves each scenario by ``jaxmm.solve_elastic``: the published NLP, then its slack weight
raised ×10 per stage, warm-started, until every complementarity product is ≤ 1e-6 N m; the
iterations column lists the stages, the objective is the published cost (eq. 32) of the answer,
and ``validate`` checks it against the task of its last stage. --smooth-start adds
``solve_elastic``'s smooth start (the squared slack penalty first; implies --elastic). Every table reports the largest
product f_z c_z or |f_z Δc_xy| (``analysis.complementarity``) of each answer, IPOPT's included.

--ipopt-slacks solves with ``Options(ipopt_slacks=True)`` (δ_w regularises the slacks too, as
IPOPT's δ_s = δ_w), in every scenario or, given a comma-separated list, in those only; the rows
it applies to are marked. --slack-start guess starts the slacks at the rows' values at the guess
itself instead of at the pushed guess (``Options.slack_start``).

--relaxation K solves with the relaxation homotopy (``Options(relaxation=K)``: Scholtes' σ driven
by μ; IPOPT unchanged). --exact [SIGMA] solves, on both sides, ``tasks.exact_complementarity(task,
SIGMA, SIGMA_T)`` (f_z c_z ≤ SIGMA [N m, default 1e-6], |f_z Δc| ≤ SIGMA_T [N m,
--planar-tolerance, default ``tasks.PLANAR_TOLERANCE``], no slack) instead of the published NLP,
ours with ``programs.EXACT_OPTIONS`` (the homotopy, μ × 0.7 per barrier problem), its κ_σ
replaced where --relaxation is given.

--max-iterations caps the iterations of our solver (``Options.max_iterations``) and
IPOPT's ``max_iter``, for quick runs.

Usage: python benchmarks/solve_scenarios.py [--scenarios take_off,jumping,...] [--knots-override N]
       [--ipopt] [--knots [60,100,200,400]] [--repeats 3] [--max-iterations M] [--coarse NC]
       [--ipopt-slacks [take_off,...]] [--slack-start pushed|guess] [--elastic] [--smooth-start]
       [--relaxation K] [--exact [SIGMA]] [--planar-tolerance SIGMA_T]
"""

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"  # before numpy is imported

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import logging  # noqa: E402
import pathlib  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402

import jaxmm  # noqa: E402  (enables float64)
from machine import format_time, log, machine_lines, render, timed  # noqa: E402
from jaxmm import analysis, io, programs, solve, tasks  # noqa: E402
from jaxmm.solver import interior_point as ip  # noqa: E402
from jaxmm.transcription import nlp as transcription  # noqa: E402
from jaxmm import stagewise  # noqa: E402
from jaxmm.transcription.variables import resample  # noqa: E402

IPOPT_TOLERANCE = 1e-4  # the paper's IPOPT tol and constr_viol_tol (physical units)
KNOT_SCENARIO = "take_off"
KNOT_COUNTS = (60, 100, 200, 400)
KNOT_BUDGET = 10  # iterations per solve of the --knots study


# ------------------------------------------------------------------------------------------ ours


def sizes(task, guess):
    """(variables, equality rows, inequality rows) of the task's stage-wise NLP."""
    nlp = transcription.stagewise_nlp(task)
    Z, theta = transcription.to_variables(task, guess)
    shapes = jax.eval_shape(stagewise.residuals, nlp, Z, theta)
    equalities = shapes.path_equality.size + shapes.transition_equality.size
    inequalities = shapes.path_inequality.size + shapes.transition_inequality.size
    return task.n_knots * task.layout.size + 1, equalities, inequalities


@jax.jit
def measure(task, trajectory):
    """(objective, max violation in the NLP units) of a trajectory, whoever computed it."""
    nlp = transcription.stagewise_nlp(task)
    Z, theta = transcription.to_variables(task, trajectory)
    return stagewise.residuals(nlp, Z, theta).cost, ip.violation(nlp, Z, theta)[0]


def solve_ours(task, guess, options, repeats, coarse=None, elastic=None):
    """(compile seconds, median solve seconds, result, coarse TaskSolution or None) of the
    compiled solve; result: a TaskSolution, or with ``elastic`` (``solve_elastic``'s keyword
    arguments) the ``ElasticSolution`` of ``solve_elastic`` (its stages share the compiled solve);
    with ``coarse`` (a number of intervals), coarse to fine: the task on that many intervals
    (``tasks.with_intervals``) solved from its own published guess, its answer resampled
    (``variables.resample``) as the guess of the task's solve; compile time: both compilations;
    solve time: both solves and the resampling."""
    if elastic is not None:
        _, compile_time = timed(lambda: programs.compile_solve(task, guess, options))
        run = lambda: (jax.block_until_ready(solve.solve_elastic(task, guess, options, **elastic)), None)  # noqa: E731
    elif coarse is None:
        compiled, compile_time = timed(lambda: programs.compile_solve(task, guess, options))
        run = lambda: (jax.block_until_ready(compiled()), None)  # noqa: E731
    else:
        coarse_task = tasks.with_intervals(task, coarse)
        (compiled_coarse, compiled), compile_time = timed(lambda: (
            programs.compile_solve(coarse_task, tasks.initial_guess(coarse_task), options),
            programs.compile_solve(task, guess, options)))  # fmt: skip

        def run():
            rough = jax.block_until_ready(compiled_coarse())
            return jax.block_until_ready(compiled(resample(rough.trajectory, task.n_knots))), rough
    times, result = [], None
    for _ in range(repeats):
        result, seconds = timed(run)
        times.append(seconds)
    return compile_time, statistics.median(times), *result


# --------------------------------------------------------------------------------------- report


def verdict(report):
    return "ok" if report.ok else f"FAILED ({len(report.failed)})"


def run_scenario(name, knots, options, repeats, urdf_path, ipopt_max_iter, slack_penalty, coarse, save=None,
                 elastic=None, exact=None):
    """Everything printed about one scenario, as a dict; IPOPT too if urdf_path is given; our
    solution written to the directory ``save`` (``jaxmm.io.save``: trajectory, multipliers, the
    per-iteration history) if given; ours by ``solve_elastic`` with ``elastic`` (its keyword arguments);
    both sides on ``tasks.exact_complementarity(task, *exact)`` where ``exact`` (σ_n, σ_t [N m]) is
    given."""
    task = tasks.scenario(name, knots=knots, slack_penalty=slack_penalty)
    task = task if exact is None else tasks.exact_complementarity(task, *exact)
    guess = tasks.initial_guess(task)
    label = name if slack_penalty == "linear" else f"{name} ({slack_penalty} slacks)"
    label = label if coarse is None else f"{label}, from N = {coarse}"
    label = f"{label}, ipopt_slacks" if options.ipopt_slacks else label
    label = label if options.slack_start == ip.Options.slack_start else f"{label}, slacks from the {options.slack_start}"
    smooth = ", smooth start" if elastic is not None and elastic["smooth_start"] else ""
    label = label if elastic is None else f"{label}, solve_elastic{smooth}"
    label = label if not options.relaxation else f"{label}, relaxation {options.relaxation:g}"
    label = label if exact is None else f"{label}, exact (σ_n = {exact[0]:g}, σ_t = {exact[1]:g} N m)"
    row = dict(name=label, N=task.n_intervals, sizes=sizes(task, guess))
    log(f"{name} N = {task.n_intervals}: compiling our solve...")
    compile_time, solve_time, result, rough = solve_ours(task, guess, options, repeats, coarse, elastic)
    log(f"{name}: solved in {format_time(solve_time)} (median of {repeats}); validating...")
    if elastic is not None:  # the stages' iterations; the answer is validated against its stage's task
        inner, (solved_task, result) = " + ".join(map(str, result.iterations)), (result.task, result.result)
    else:
        solved_task = task
        inner = str(int(result.solution.iterations)) if rough is None else \
            f"{int(rough.solution.iterations)} + {int(result.solution.iterations)}"
    objective, violation = (float(v) for v in measure(task, result.trajectory))  # the published cost (eq. 32)
    row["ours"] = dict(
        compile=compile_time, solve=solve_time, objective=objective, violation=violation,
        outer=int(result.solution.barrier_updates), inner=inner, product=largest_product(result.trajectory),
        solves=per_iteration(result.solution, "linear_solves"),
        factorisations=per_iteration(result.solution, "factorisations"), status=result.status.message,
        report=analysis.validate(solved_task, result.trajectory),
    )  # fmt: skip
    if save is not None:
        path = pathlib.Path(save) / f"{name}_N{task.n_intervals}.npz"
        io.save(path, task, result)
        log(f"{name}: solution written to {path}")
    if urdf_path is not None:
        from jaxmm.reference import solve_ipopt  # the reference extra (casadi, adam-robotics)

        log(f"{name}: IPOPT (slow: ~10 min at take-off N = 70)...")
        max_iter = {} if ipopt_max_iter is None else dict(max_iter=ipopt_max_iter)
        trajectory, info = solve_ipopt(task, urdf_path, guess, tol=IPOPT_TOLERANCE, print_level=0, **max_iter)
        objective, violation = (float(v) for v in measure(task, trajectory))
        row["ipopt"] = dict(info, objective_jax=objective, violation_jax=violation, product=largest_product(trajectory),
                            report=analysis.validate(task, trajectory))
        log(f"{name}: IPOPT {info['status']} in {format_time(info['wall_time'])}")
    return row


def largest_product(trajectory):
    """The largest complementarity product f_z c_z or |f_z Δc_xy| [N m] (``analysis.complementarity``)."""
    measure = analysis.complementarity(trajectory)
    return max(measure["normal"], measure["planar"])


def per_iteration(solution, column):
    """Mean of a history column (``ip.HISTORY_COLUMNS``) over the iterations: "linear_solves" (block
    solves: refinements, second-order corrections), "factorisations" (the inertia correction's
    work, in whole factorisations)."""
    history = np.asarray(solution.history)[: int(solution.iterations)]
    return float(np.nanmean(history[:, ip.HISTORY_COLUMNS.index(column)])) if len(history) else 0.0


def scenario_table(rows):
    header = ("scenario", "N", "variables", "equalities", "inequalities", "μ updates", "iterations", "solves / it.",
              "factorisations / it.", "compile", "solve", "objective", "max violation", "largest product", "status",
              "validate")  # fmt: skip
    lines = [
        (r["name"], r["N"], *r["sizes"], r["ours"]["outer"], r["ours"]["inner"], f"{r['ours']['solves']:.1f}",
         f"{r['ours']['factorisations']:.2f}",
         format_time(r["ours"]["compile"]), format_time(r["ours"]["solve"]), f"{r['ours']['objective']:.6g}",
         f"{r['ours']['violation']:.2e}", f"{r['ours']['product']:.1e}", r["ours"]["status"], verdict(r["ours"]["report"]))
        for r in rows
    ]  # fmt: skip
    return render(header, lines)


def ipopt_table(rows):
    header = ("scenario", "N", "IPOPT build", "IPOPT setup", "IPOPT solve", "IPOPT it.", "objective", "max violation",
              "largest product", "IPOPT status", "validate", "ours compile", "ours solve", "ours objective", "ours violation",
              "speed-up solve", "speed-up incl. compile", "speed-up end to end")  # fmt: skip
    lines = []
    for r in rows:
        ours, ipopt = r["ours"], r["ipopt"]
        ours_total = ours["compile"] + ours["solve"]
        ipopt_total = ipopt["build_time"] + ipopt["setup_time"] + ipopt["wall_time"]
        lines.append((
            r["name"], r["N"], format_time(ipopt["build_time"]), format_time(ipopt["setup_time"]),
            format_time(ipopt["wall_time"]), ipopt["iterations"], f"{ipopt['objective_jax']:.6g}",
            f"{ipopt['violation_jax']:.2e}", f"{ipopt['product']:.1e}", ipopt["status"], verdict(ipopt["report"]),
            format_time(ours["compile"]), format_time(ours["solve"]), f"{ours['objective']:.6g}",
            f"{ours['violation']:.2e}", f"{ipopt['wall_time'] / ours['solve']:.3g}×",
            f"{ipopt['wall_time'] / ours_total:.3g}×", f"{ipopt_total / ours_total:.3g}×",
        ))  # fmt: skip
    return render(header, lines)


def failed_lines(rows):
    lines = []
    for r in rows:
        for side in ("ours", "ipopt"):
            if side in r and not r[side]["report"].ok:
                lines.append(f"{r['name']} ({side}): failed checks: {', '.join(r[side]['report'].failed)}")
    return lines


def knot_study(counts, budget, repeats):
    """One table row per N: compile, solve, iterations, per iteration, per iteration / N."""
    options = dataclasses.replace(solve.DEFAULT_OPTIONS, max_iterations=budget)
    lines, first = [], None
    for knots in counts:
        task = tasks.scenario(KNOT_SCENARIO, knots=knots)
        guess = tasks.initial_guess(task)
        log(f"{KNOT_SCENARIO} N = {knots}: compiling (budget {budget} iterations)...")
        compile_time, solve_time, result, _ = solve_ours(task, guess, options, repeats)
        inner = int(result.solution.iterations)
        per_iteration = solve_time / max(inner, 1)
        first = first or (knots, per_iteration)
        lines.append((
            knots, sizes(task, guess)[0], format_time(compile_time), format_time(solve_time), inner,
            format_time(per_iteration), format_time(per_iteration / knots),
            f"{per_iteration / first[1]:.3g}× (N {knots / first[0]:.3g}×)", result.status.name.lower(),
        ))  # fmt: skip
    header = ("N", "variables", "compile", "solve", "iterations", "per iteration", "per iteration / N",
              "per iteration vs first row", "status")  # fmt: skip
    return render(header, lines)


def parse_names(parser, text, default):
    """The scenario names of a comma-separated list (``-`` for ``_``), ``default`` if None."""
    if text is None:
        return default
    names = [s.strip().replace("-", "_") for s in text.split(",") if s.strip()]
    for name in names:
        if name not in tasks.SCENARIOS:
            parser.error(f"unknown scenario {name!r}; scenarios: {', '.join(tasks.SCENARIOS)}")
    return names


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", default=None,
                        help=f"comma-separated, from {', '.join(tasks.SCENARIOS)} (default: all)")  # fmt: skip
    parser.add_argument("--knots-override", type=int, default=None, help="N for every scenario instead of the published one")
    parser.add_argument("--ipopt", action="store_true", help="also solve every scenario with IPOPT (slow)")
    parser.add_argument("--knots", nargs="?", const=",".join(map(str, KNOT_COUNTS)), default=None,
                        help=f"time per iteration on {KNOT_SCENARIO} for these N (default {KNOT_COUNTS})")  # fmt: skip
    parser.add_argument("--repeats", type=int, default=3, help="timed runs of our compiled solve (the median is reported)")
    parser.add_argument("--max-iterations", type=int, default=None, help="iteration limit of both solvers")
    parser.add_argument("--slack-penalty", choices=tasks.SLACK_PENALTIES, default="linear",
                        help="penalty of the complementarity slacks: linear (the published runs, default) or squared (the paper's text)")
    parser.add_argument("--ipopt-slacks", nargs="?", const="all", default=None, metavar="SCENARIOS",
                        help="regularise the slacks as IPOPT does (ip.Options.ipopt_slacks: δ_w on them) "
                             "in every scenario, or only in these (comma-separated)")
    parser.add_argument("--slack-start", choices=ip.SLACK_STARTS, default=ip.Options.slack_start,
                        help="where the slacks start (ip.Options.slack_start): at the rows of the pushed guess "
                             "(default, IPOPT's) or of the guess itself")
    parser.add_argument("--coarse", type=int, default=None,
                        help="solve each scenario from the solution of its version on this many intervals (same horizons)")
    parser.add_argument("--elastic", action="store_true",
                        help="solve by jaxmm.solve_elastic (the published NLP, then its slack weight raised to "
                             "exact complementarity); iterations per stage")
    parser.add_argument("--smooth-start", action="store_true",
                        help="solve_elastic with its smooth start (the squared slack penalty first); implies --elastic")
    parser.add_argument("--save", default=None, metavar="DIR",
                        help="write each of our solutions to DIR/<scenario>_N<N>.npz (jaxmm.io.save; with its "
                             "per-iteration history)")
    parser.add_argument("--relaxation", type=float, default=None, metavar="K",
                        help="our solver with the relaxation homotopy, Options(relaxation=K) (default: off; "
                             "the κ_σ of programs.EXACT_OPTIONS with --exact)")
    parser.add_argument("--exact", type=float, nargs="?", const=1e-6, default=None, metavar="SIGMA",
                        help="both sides on tasks.exact_complementarity(task, SIGMA) (default SIGMA 1e-6 N m)")
    parser.add_argument("--planar-tolerance", type=float, default=tasks.PLANAR_TOLERANCE, metavar="SIGMA_T",
                        help="with --exact: the planar rows' σ_t [N m] (default tasks.PLANAR_TOLERANCE)")
    args = parser.parse_args()
    if args.relaxation is None:
        args.relaxation = 0.0 if args.exact is None else programs.EXACT_OPTIONS.relaxation
    if not (args.relaxation >= 0 and np.isfinite(args.relaxation)):
        parser.error(f"--relaxation must be a finite number ≥ 0, got {args.relaxation}")
    for flag, value in (("--exact", args.exact), ("--planar-tolerance", args.planar_tolerance)):
        if value is not None and not (value >= 0 and np.isfinite(value)):
            parser.error(f"{flag} must be a finite number ≥ 0 [N m], got {value}")
    exact = None if args.exact is None else (args.exact, args.planar_tolerance)
    elastic = dict(smooth_start=args.smooth_start) if args.elastic or args.smooth_start else None
    if elastic is not None and args.coarse is not None:
        parser.error("--elastic and --coarse cannot be combined")
    if args.save is not None:
        pathlib.Path(args.save).mkdir(parents=True, exist_ok=True)

    run_scenarios = args.scenarios is not None or args.knots is None
    names = parse_names(parser, args.scenarios, default=list(tasks.SCENARIOS))
    base = solve.DEFAULT_OPTIONS if args.exact is None else programs.EXACT_OPTIONS
    options = dataclasses.replace(base, slack_start=args.slack_start, relaxation=args.relaxation)
    if args.max_iterations is not None:
        options = dataclasses.replace(options, max_iterations=args.max_iterations)
    slack_names = names if args.ipopt_slacks == "all" else parse_names(parser, args.ipopt_slacks, default=[])

    logging.getLogger("yourdfpy").setLevel(logging.ERROR)  # unresolved mesh files are irrelevant
    started = time.perf_counter()
    header = machine_lines(("jax", "jaxlib", "numpy") + (("casadi", "adam-robotics") if args.ipopt else ()))

    rows = []
    if run_scenarios:
        with tempfile.NamedTemporaryFile(suffix=".urdf") as urdf:
            if args.ipopt:
                urdf.write(jaxmm.assemble_urdf(jaxmm.robots.ironcub_description()).write_xml_string())
                urdf.flush()
            for name in names:
                rows.append(run_scenario(
                    name, args.knots_override, dataclasses.replace(options, ipopt_slacks=name in slack_names), args.repeats,
                    urdf.name if args.ipopt else None, args.max_iterations,
                    args.slack_penalty, args.coarse, args.save, elastic, exact,
                ))
    knot_table = None
    if args.knots is not None:
        counts = [int(n) for n in args.knots.split(",")]
        knot_table = knot_study(counts, args.max_iterations or KNOT_BUDGET, args.repeats)

    print("\n".join(header))
    if rows:
        print(
            f"Scenarios from the published initial guess, {'N = ' + str(args.knots_override) if args.knots_override else 'published N'}"
            f"{'' if args.coarse is None else f', ours through the solution on N = {args.coarse} intervals (iterations: coarse + fine)'}; "
            f"our solver: tolerance {options.tolerance:g} (violation), stationarity {options.stationarity:g}, "
            f"max {options.max_iterations} iterations; solve = median of {args.repeats} runs of the compiled solve; "
            "objective and max violation (NLP units) of the returned trajectory by the same JAX function for both sides"
        )
        print()
        print(scenario_table(rows))
        lines = failed_lines(rows)
        if any("ipopt" in r for r in rows):
            print()
            print(f"IPOPT (MUMPS, exact Hessian, tol {IPOPT_TOLERANCE:g} physical units), one run each; "
                  "speed-ups: IPOPT solve / ours solve, IPOPT solve / (ours compile + solve), "
                  "(IPOPT build + setup + solve) / (ours compile + solve)")  # fmt: skip
            print()
            print(ipopt_table(rows))
        if lines:
            print()
            print("\n".join(lines))
        for r in rows:
            for side, label in (("ours", "ours"), ("ipopt", "IPOPT")):
                if side in r:
                    print()
                    print(f"validate: {r['name']} N = {r['N']}, {label}: {'ok' if r[side]['report'].ok else 'FAILED'}")
                    print(r[side]["report"])
    if knot_table is not None:
        print()
        print(f"Time per iteration on {KNOT_SCENARIO} against N, budget {args.max_iterations or KNOT_BUDGET} "
              f"iterations from the published guess; solve = median of {args.repeats} runs")  # fmt: skip
        print()
        print(knot_table)
    print()
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"Total benchmark time {time.perf_counter() - started:.0f} s; load average at the end {load}.")


if __name__ == "__main__":
    main()
