"""The ``jaxmm`` command line: solve the published scenarios, compare with IPOPT, describe robots.

    jaxmm scenarios                                   the four scenarios and their settings
    jaxmm solve take-off [--knots N] [--target x y z] [--urdf PATH] [--torque-limits] [--out DIR]
                         [--time-budget S]
    jaxmm multistart take-off --guesses B [--seed S]  B sampled guesses, ranked; the best written
    jaxmm compare take-off [--knots N]                ours and the CasADi/IPOPT reference
    jaxmm robot [--urdf PATH]                         a robot summary

``solve`` writes to its output directory the solution (``solution.npz``, see ``jaxmm.io``), the
validation report (``validation.txt``), a summary (``summary.json``, with the joint torques the
plan needs against the motors' limits), the figures and an animation. Progress (compiling, then
every iteration) is shown on a terminal and stays quiet when the output is piped or ``CI`` is set.
With ``--time-budget S``, the end of S seconds of iterating or a Ctrl-C stops the solve with its
last iterate, which is written like any other (status ``INTERRUPTED`` or ``TIME_LIMIT`` in the
summary; exit code 1); a second Ctrl-C aborts. ``--torque-limits`` adds the joint-torque bounds
(``Task.joint_torque_limits``), which the paper's problem does not have.

Compiled programs are kept on disk (``jaxmm.compilation.use_persistent_cache``; ``--cache-dir``,
default ``~/.cache/jaxmm/xla``, or ``$JAX_COMPILATION_CACHE_DIR`` when set; ``--no-cache``): the
first solve of a scenario at a knot count compiles, the next ones load the programs (without
tracing them: ``jaxmm.compilation.ExecutableStore``).

``multistart`` solves B guesses sampled around the published one (``batch.sample_guesses``) with
``batch.solve_batch`` and writes the ranked summary (``summary.txt``, ``summary.json``), the best
instance's solution (``best.npz``) and a figure of the distinct contact schedules found
(``schedules.png``); progress is one line per finished instance.
"""

import argparse
import dataclasses
import json
import logging
import os
import pathlib
import sys
import tempfile
import threading
import time

ERRORS = (ValueError, KeyError, OSError, TypeError, ImportError)


class Progress:
    """Status lines on a terminal: a compile timer, then one line per iteration, rewritten in
    place. Silent (but for the final summaries) when ``live`` is False."""

    def __init__(self, live, stream=sys.stderr):
        self.live, self.stream = live, stream
        self._stop = threading.Event()

    @staticmethod
    def detect(quiet):
        return not quiet and sys.stderr.isatty() and not os.environ.get("CI")

    def _write(self, text):
        self.stream.write(f"\r\033[K{text}")
        self.stream.flush()

    def compiling(self, what):
        """A context manager showing the elapsed compile time."""
        progress = self

        class _Timer:
            def __enter__(self):
                self.start = time.perf_counter()
                if progress.live:
                    progress._stop.clear()
                    self.thread = threading.Thread(target=self._tick, daemon=True)
                    self.thread.start()
                return self

            def _tick(self):
                while not progress._stop.wait(0.5):
                    progress._write(f"compiling {what}: {time.perf_counter() - self.start:.0f} s")

            def __exit__(self, *exc):
                self.seconds = time.perf_counter() - self.start
                if progress.live:
                    progress._stop.set()
                    self.thread.join()
                    progress._write(f"compiled {what} in {self.seconds:.1f} s\n")

        return _Timer()

    def iteration(self, iteration, record):
        """The solver's per-iteration callback (``Options.progress``): record is a history row."""
        from jaxmm.solver.interior_point import HISTORY_COLUMNS

        if len(record) != len(HISTORY_COLUMNS):
            raise ValueError(f"a history row has {len(HISTORY_COLUMNS)} entries ({', '.join(HISTORY_COLUMNS)}), "
                             f"got {len(record)}")
        row = {name: float(v) for name, v in zip(HISTORY_COLUMNS, record)}
        self._write(
            f"iteration {int(iteration) + 1:5d}{'r' if row['restoration'] == 1 else ' '} "
            f"objective {row['objective']:.6e}  violation {row['violation']:.1e}  "
            f"stationarity {row['stationarity']:.1e}  barrier μ {row['barrier']:.0e}  step {row['step_length']:.2g}  "
            f"regularisation {row['regularisation']:.0e}  factorisations {row['factorisations']:.2f}  "
            f"solves {row['linear_solves']:.0f}"
        )

    def done(self):
        if self.live:
            self.stream.write("\n")
            self.stream.flush()


def _ironcub_like(urdf):
    """iRonCub's joints, jets, contact corners and standing pose on another URDF of it."""
    import jaxmm

    default = jaxmm.load_ironcub()
    return jaxmm.load_robot(
        urdf,
        joints=default.model.joint_names,
        jet_frames=default.jet_frames,
        contact_frames=default.contact_frames,
        standing_configuration=default.standing_configuration,
        reference_mass=default.reference_mass,
        check_inertia=False,
    )


def scenario_task(args):
    """The scenario of ``args`` (name, knots, target, URDF, --torque-limits, --exact,
    --planar-tolerance) as a Task. With fewer (or more) knots than published, the time-step bounds
    scale so that the horizon stays the published one; with --exact σ_n [--planar-tolerance σ_t],
    ``tasks.exact_complementarity(task, σ_n, σ_t)``."""
    from jaxmm import tasks

    overrides = {} if args.target is None else dict(final_com=args.target)
    if getattr(args, "torque_limits", False):
        overrides["joint_torque_limits"] = True
    robot = None if args.urdf is None else _ironcub_like(args.urdf)
    task = tasks.scenario(args.scenario, robot=robot, knots=args.knots, keep_horizon=True, **overrides)
    exact, planar = getattr(args, "exact", None), getattr(args, "planar_tolerance", None)
    if exact is None:
        return task
    return tasks.exact_complementarity(task, exact) if planar is None else tasks.exact_complementarity(task, exact, planar)


def solver_options(args):
    """The solver options of ``args`` (--max-iterations, --ipopt-slacks, --relaxation): from
    ``programs.EXACT_OPTIONS`` with --exact (the homotopy and its barrier schedule; --relaxation
    sets its κ_σ), from ``programs.DEFAULT_OPTIONS`` otherwise."""
    from jaxmm import programs

    exact = getattr(args, "exact", None) is not None
    options = programs.EXACT_OPTIONS if exact else programs.DEFAULT_OPTIONS
    if args.max_iterations is not None:
        options = dataclasses.replace(options, max_iterations=args.max_iterations)
    if getattr(args, "ipopt_slacks", False):
        options = dataclasses.replace(options, ipopt_slacks=True)
    relaxation = getattr(args, "relaxation", None)
    if relaxation is not None:
        options = dataclasses.replace(options, relaxation=relaxation)
    return options


def _solve(task, args, progress):
    from jaxmm import programs

    options = solver_options(args)
    if progress.live:
        options = dataclasses.replace(options, progress=progress.iteration)
    with progress.compiling(f"the solve of {task.name} (N = {task.n_intervals})") as compiling:
        budget = getattr(args, "time_budget", None)
        run = programs.compile_solve(task, options=options, time_budget=budget, interruptible=budget is not None)
    start = time.perf_counter()
    result = run()
    result.solution.status.block_until_ready()
    progress.done()
    return result, compiling.seconds, time.perf_counter() - start


def _torque_summary(torques):
    """The joint-torque numbers of a ``TorqueReport`` for summary.json."""
    import numpy as np

    name, knot, torque, limit = torques.worst
    return dict(
        largest_load=float(torques.load.max()), worst_joint=name, worst_knot=knot, worst_torque=torque, worst_limit=limit,
        saturated={joint: dict(knots=list(knots), largest_load=load) for joint, (knots, load) in torques.saturated.items()},
        base_force_max=float(np.linalg.norm(torques.base_force, axis=1).max()),
        base_torque_max=float(np.linalg.norm(torques.base_torque, axis=1).max()),
    )


def _solve_command(args):
    from jaxmm import analysis, io

    progress = Progress(Progress.detect(args.quiet))
    task = scenario_task(args)
    out = pathlib.Path(args.out if args.out is not None else pathlib.Path("jaxmm-results") / task.name)
    out.mkdir(parents=True, exist_ok=True)
    result, compile_time, solve_time = _solve(task, args, progress)
    report = analysis.validate(task, result.trajectory)
    solution = result.solution
    print(f"{task.name}: N = {task.n_intervals}, {result.status.message}")
    print(
        f"  {int(solution.iterations)} iterations, compile {compile_time:.1f} s, solve {solve_time:.1f} s, "
        f"objective {float(solution.objective):.6e}, max violation {float(solution.violation):.1e}"
    )
    print(f"  validate: {'ok' if report.ok else 'FAILED: ' + ', '.join(report.failed)}")
    print(f"  joint torques: {report.torques}".replace("\n", "\n  "))
    written = [io.save(out / "solution.npz", task, result)]
    (out / "validation.txt").write_text(str(report) + "\n")
    summary = dict(
        scenario=task.name, knots=task.n_intervals, status=result.status.name, message=result.status.message,
        iterations=int(solution.iterations), compile_seconds=compile_time, solve_seconds=solve_time,
        objective=float(solution.objective), violation=float(solution.violation),
        violation_per_family={k: float(v) for k, v in result.violation_per_family.items()},
        validate_ok=report.ok, failed_checks=list(report.failed),
        flight_knots=list(report.flight_knots), total_time=float(result.trajectory.total_time),
        torques=_torque_summary(report.torques),
    )
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    written += [out / "validation.txt", out / "summary.json"]
    if not args.no_figures:
        from jaxmm.analysis import animation, plots

        written += list(plots.save_figures(task, result, out).values())
        if not args.no_animation:
            written.append(animation.animate(task, result.trajectory, out / "motion.gif"))
    print(f"  wrote {len(written)} files to {out}/: " + ", ".join(pathlib.Path(p).name for p in written))
    return 0 if result.status.name == "CONVERGED" and report.ok else 1


def _multistart_command(args):
    import jax

    from jaxmm import analysis, batch, io

    progress = Progress(Progress.detect(args.quiet))
    task = scenario_task(args)
    out = pathlib.Path(args.out if args.out is not None else pathlib.Path("jaxmm-results") / f"{task.name}-multistart")
    out.mkdir(parents=True, exist_ok=True)
    options = solver_options(args)
    guesses = batch.sample_guesses(task, jax.random.key(args.seed), args.guesses)
    start = time.perf_counter()
    solved = batch.solve_batch(task, guesses, options, strategy=args.strategy, time_budget=args.time_budget,
                               interruptible=args.time_budget is not None,
                               progress=(lambda report: progress._write(str(report))) if progress.live else None)
    seconds = time.perf_counter() - start
    progress.done()
    summary = batch.summarise(task, solved)
    best = batch.instance(solved, summary.best.index)
    report = analysis.validate(task, best.trajectory)
    print(f"{task.name}: N = {task.n_intervals}, {args.guesses} guesses (seed {args.seed}) in {seconds:.1f} s, "
          f"compiling included")
    print(str(summary).split("\n")[0])
    print(f"  best: instance {summary.best.index}, {summary.best.status.name.lower()}, objective "
          f"{summary.best.objective:.6e}; validate: {'ok' if report.ok else 'FAILED: ' + ', '.join(report.failed)}")
    (out / "summary.txt").write_text(str(summary) + "\n")
    ranking = [dict(instance=r.index, status=r.status.name, objective=r.objective, violation=r.violation,
                    iterations=r.iterations, schedule=r.schedule + 1) for r in summary.ranking]
    (out / "summary.json").write_text(json.dumps(dict(
        scenario=task.name, knots=task.n_intervals, guesses=args.guesses, seed=args.seed, seconds=seconds,
        best_validate_ok=report.ok, ranking=ranking,
        schedules=[dict(members=list(g.members), flight_knots=list(g.flight_knots)) for g in summary.schedules],
    ), indent=2) + "\n")
    written = [io.save(out / "best.npz", task, best), out / "summary.txt", out / "summary.json"]
    if not args.no_figures:
        from jaxmm.analysis import plots

        written.append(out / "schedules.png")
        plots.plot_schedules(summary).savefig(written[-1], dpi=120)
    print(f"  wrote {len(written)} files to {out}/: " + ", ".join(pathlib.Path(p).name for p in written))
    return 0 if summary.best.status.name == "CONVERGED" and report.ok else 1


def _scenarios_command(args):
    from jaxmm import tasks

    print(f"{'scenario':22s} {'N':>4s}  {'horizon [s]':12s} {'initial CoM [m]':18s} {'final CoM [m]':18s} {'mid height':10s} jets  description")
    for name, spec in tasks.SCENARIOS.items():
        n, defaults = spec["knots"], tasks.build_task.__kwdefaults__
        horizon = f"{defaults['min_dt'] * n:.1f}–{defaults['max_dt'] * n:.1f}"
        mid = f"≥ {spec['mid_com_height']:.2f} m" if spec.get("mid_com_height") is not None else "-"
        fmt = lambda v: "(" + ", ".join(f"{x:g}" for x in v) + ")"  # noqa: E731
        print(
            f"{name.replace('_', '-'):22s} {n:4d}  {horizon:12s} {fmt(spec['initial_com']):18s} {fmt(spec['final_com']):18s} "
            f"{mid:10s} {'yes' if spec.get('jets', True) else 'no ':4s}  {spec['description']}"
        )


def _compare_command(args):
    try:
        from jaxmm.reference import solve_ipopt
    except ImportError as error:
        raise ImportError(f"`jaxmm compare` needs the reference extra (pip install 'jaxmm[reference]'): {error}") from None
    import jaxmm
    from jaxmm import analysis
    from jaxmm.tasks import initial_guess

    progress = Progress(Progress.detect(args.quiet))
    task = scenario_task(args)
    result, compile_time, solve_time = _solve(task, args, progress)
    logging.getLogger("yourdfpy").setLevel(logging.ERROR)
    with tempfile.TemporaryDirectory() as directory:
        urdf = pathlib.Path(args.urdf) if args.urdf else pathlib.Path(directory) / "robot.urdf"
        if not args.urdf:
            urdf.write_bytes(jaxmm.assemble_urdf(jaxmm.robots.ironcub_description()).write_xml_string())
        if progress.live:
            progress.stream.write("solving with IPOPT (CasADi reference)…\n")
        max_iter = {} if args.max_iterations is None else dict(max_iter=args.max_iterations)
        trajectory, info = solve_ipopt(task, urdf, initial_guess(task), tol=1e-4, **max_iter)
    ours_report, ipopt_report = analysis.validate(task, result.trajectory), analysis.validate(task, trajectory)
    rows = [
        ("", "jaxmm", "IPOPT"),
        ("status", result.status.name, str(info["status"])),
        ("iterations", str(int(result.solution.iterations)), str(info["iterations"])),
        ("build/compile [s]", f"{compile_time:.1f}", f"{info['build_time'] + info.get('setup_time', 0.0):.1f}"),
        ("solve [s]", f"{solve_time:.1f}", f"{info['wall_time']:.1f}"),
        ("objective", f"{float(result.solution.objective):.8e}", f"{info['objective']:.8e}"),
        ("max violation", f"{float(result.solution.violation):.1e}", f"{info['max_violation']:.1e}"),
        ("validate", "ok" if ours_report.ok else "FAILED", "ok" if ipopt_report.ok else "FAILED"),
    ]
    print(f"{task.name}, N = {task.n_intervals}, from the published initial guess")
    for label, ours, theirs in rows:
        print(f"  {label:18s} {ours:>18s} {theirs:>18s}")
    print(f"  IPOPT solve time / ours: {info['wall_time'] / solve_time:.3g}×")
    return 0


def _robot_command(args):
    from jaxmm.robots import load_ironcub, load_robot

    robot = load_ironcub() if args.urdf is None else load_robot(args.urdf, joints=args.joints)
    print(robot.summary())


def _scenario_arguments(parser):
    parser.add_argument("scenario", help="take-off, take-off-and-landing, walk-to-fly or jumping")
    parser.add_argument("--knots", type=int, help="N (default: the published one; the horizon is kept)")
    parser.add_argument("--target", type=float, nargs=3, metavar=("X", "Y", "Z"), help="final CoM [m]")
    parser.add_argument("--urdf", help="another URDF of iRonCub (same joint, jet and contact frame names)")
    parser.add_argument("--torque-limits", action="store_true",
                        help="bound every joint torque by the URDF's effort limit (not in the paper's problem)")
    parser.add_argument("--max-iterations", type=int, help="solver iteration limit (default 3000)")
    parser.add_argument("--quiet", action="store_true", help="no progress display")
    parser.add_argument("--ipopt-slacks", action="store_true",
                        help="regularise the inequality slacks as IPOPT does (δ_s = δ_w; take-off-and-landing "
                             "converges in fewer iterations; see the README)")
    parser.add_argument("--relaxation", type=float, metavar="K",
                        help="relax the contact complementarity by σ = K (μ − μ_floor) / s_f, driven to 0 with the "
                             "barrier parameter (Scholtes' homotopy; 1e-3 serves the published sizes; default: off, "
                             "1e-3 with --exact)")
    parser.add_argument("--exact", type=float, nargs="?", const=1e-6, metavar="SIGMA",
                        help="contact complementarity within SIGMA [N m, default 1e-6] and no slack instead of the "
                             "published relaxation (tasks.exact_complementarity), solved through the homotopy "
                             "(--relaxation 1e-3 unless given) with μ × 0.7 per barrier problem "
                             "(programs.EXACT_OPTIONS)")
    parser.add_argument("--planar-tolerance", type=float, metavar="SIGMA_T",
                        help="with --exact: the planar complementarity within SIGMA_T [N m, default 1e-3: a slip of "
                             "at most 10 µm per interval under 100 N]")
    parser.add_argument("--time-budget", type=float, metavar="S",
                        help="stop iterating after S seconds and keep the last iterate (default: no limit)")
    cache = parser.add_mutually_exclusive_group()
    cache.add_argument("--cache-dir", metavar="DIR",
                       help="keep compiled programs in DIR (default: ~/.cache/jaxmm/xla, or $JAX_COMPILATION_CACHE_DIR)")
    cache.add_argument("--no-cache", action="store_true", help="compile without the on-disk cache")


def cache_directory(args):
    """The directory the command keeps compiled programs in, or None for none: ``--cache-dir``,
    else none with ``--no-cache``, else JAX's own setting (``$JAX_COMPILATION_CACHE_DIR``) when
    there is one, else ``compilation.default_cache_directory()``."""
    from jaxmm import compilation

    if getattr(args, "cache_dir", None) is not None:
        return pathlib.Path(args.cache_dir)
    if getattr(args, "no_cache", True):  # commands that compile nothing have neither option
        return None
    import jax

    return pathlib.Path(jax.config.jax_compilation_cache_dir or compilation.default_cache_directory())


def main(argv=None):
    parser = argparse.ArgumentParser(prog="jaxmm", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    solve = commands.add_parser("solve", help="solve a scenario; write solution, report, figures and animation")
    _scenario_arguments(solve)
    solve.add_argument("--out", help="output directory (default: jaxmm-results/<scenario>)")
    solve.add_argument("--no-figures", action="store_true", help="write no figures and no animation")
    solve.add_argument("--no-animation", action="store_true", help="write the figures but no animation")
    solve.set_defaults(run=_solve_command)
    scenarios = commands.add_parser("scenarios", help="list the published scenarios and their settings")
    scenarios.set_defaults(run=_scenarios_command)
    multistart = commands.add_parser("multistart", help="solve a scenario from many sampled guesses; rank them")
    _scenario_arguments(multistart)
    multistart.add_argument("--guesses", type=int, required=True, metavar="B", help="how many sampled guesses")
    multistart.add_argument("--seed", type=int, default=0, help="seed of the sampled guesses (default 0)")
    multistart.add_argument("--strategy", choices=("queue", "processes", "slots"),
                            help="how the batch runs (default: one process per core on a CPU, vmapped slots on "
                                 "an accelerator; see jaxmm.schedule)")
    multistart.add_argument("--out", help="output directory (default: jaxmm-results/<scenario>-multistart)")
    multistart.add_argument("--no-figures", action="store_true", help="write no figure")
    multistart.set_defaults(run=_multistart_command)
    compare = commands.add_parser("compare", help="solve a scenario with jaxmm and with IPOPT, side by side")
    _scenario_arguments(compare)
    compare.set_defaults(run=_compare_command)
    robot = commands.add_parser("robot", help="print a robot summary (default: iRonCub)")
    robot.add_argument("--urdf", help="a URDF file (default: the assembled iRonCub)")
    robot.add_argument("--joints", nargs="+", help="optimised joints (default: all moving joints)")
    robot.set_defaults(run=_robot_command)
    args = parser.parse_args(argv)
    if getattr(args, "knots", None) is not None and args.knots < 2:
        parser.error(f"--knots must be at least 2, got {args.knots}")
    if getattr(args, "guesses", None) is not None and args.guesses < 1:
        parser.error(f"--guesses must be at least 1, got {args.guesses}")
    for flag, unit in (("relaxation", ""), ("exact", " [N m]"), ("planar_tolerance", " [N m]")):
        value = getattr(args, flag, None)
        if value is not None and not 0 <= value < float("inf"):
            parser.error(f"--{flag.replace('_', '-')} must be a finite number ≥ 0{unit}, got {value}")
    if getattr(args, "planar_tolerance", None) is not None and args.exact is None:
        parser.error("--planar-tolerance applies to the exact task: give --exact too")
    budget = getattr(args, "time_budget", None)
    if budget is not None and not 0 < budget < float("inf"):
        parser.error(f"--time-budget must be a positive number of seconds, got {budget}")
    try:
        directory = cache_directory(args)
        if directory is not None:
            from jaxmm import compilation

            compilation.use_persistent_cache(directory)
        return args.run(args) or 0
    except ERRORS as error:
        print(f"jaxmm {args.command}: error: {error}", file=sys.stderr)
        return 2
