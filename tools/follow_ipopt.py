"""Follow IPOPT iteration by iteration: our solver and the IPOPT reference from the same guess,
side by side per iteration, and the first iteration where their paths part.

Per iteration: the objective after the step (NLP units, both sides), the constraint violation
(ours: max over every group in the NLP's units; IPOPT's ``inf_pr``: its unscaled violation),
the Hessian regularisation δ_w as log10 (IPOPT's ``lg(rg)``, "-" for none) and the primal step
length α (IPOPT's ``alpha_pr``; its letter says which filter rule accepted it, "r" after the
iteration number marks its restoration phase, which we do not have). The paths "part" at the
first iteration whose objectives differ by more than --part (relative).

Both sides start from the same point: IPOPT runs with ``bound_relax_factor`` 0 (by default it
relaxes every bound by 1e-8 relative, which moves its start and its first steps); everything
else as ``solve_scenarios.py --ipopt`` (``tol`` 1e-4, exact Hessian, MUMPS). IPOPT's log is read
from its ``output_file`` at print level 5. The first iteration at which the two logs part is
where our Newton step differs from IPOPT's.

Not a timing benchmark: both solves are capped at --iterations and not timed.

Usage: python tools/follow_ipopt.py [--scenario take_off] [--knots 14] [--iterations 60]
       [--part 1e-4]
"""

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"  # before numpy is imported

import pathlib  # noqa: E402
import sys  # noqa: E402

# benchmarks/machine.py: the machine, versions and tables that the benchmarks print too
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import logging  # noqa: E402
import math  # noqa: E402
import re  # noqa: E402
import tempfile  # noqa: E402

import numpy as np  # noqa: E402

import jaxmm  # noqa: E402  (enables float64)
from machine import machine_lines, render  # noqa: E402
from jaxmm import solve, tasks  # noqa: E402

# One row of IPOPT's iteration log: iter[r] objective inf_pr inf_du lg(mu) ||d|| lg(rg) alpha_du alpha_pr ls
IPOPT_ROW = re.compile(r"^\s*(\d+)(r?)\s+(\S+)\s+(\S+)\s+\S+\s+\S+\s+\S+\s+(\S+)\s+\S+\s+(\S+)\s+\d+\s*$")


def ipopt_iterations(log_text):
    """[(iteration, restoration, objective, inf_pr, lg(rg) text, alpha_pr text)] from IPOPT's
    log, iteration 0 (the start) left out."""
    rows = []
    for line in log_text.splitlines():
        match = IPOPT_ROW.match(line)
        if match and int(match.group(1)) > 0:
            iteration, restoration, objective, violation, regularisation, alpha = match.groups()
            rows.append((int(iteration), restoration == "r", float(objective), float(violation), regularisation, alpha))
    return rows


def our_iterations(task, iterations):
    """The history rows (``interior_point.HISTORY_COLUMNS``) of our solve from the published guess."""
    options = dataclasses.replace(solve.DEFAULT_OPTIONS, max_iterations=iterations)
    history = np.asarray(solve.solve_task(task, options=options).solution.history)
    return history[~np.isnan(history[:, 0])]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenario", default="take_off")
    parser.add_argument("--knots", type=int, default=14, help="N, with the published horizon (keep_horizon)")
    parser.add_argument("--iterations", type=int, default=60, help="iterations of each solver")
    parser.add_argument("--part", type=float, default=1e-4, help="relative objective difference at which the paths part")
    args = parser.parse_args()
    logging.getLogger("yourdfpy").setLevel(logging.ERROR)
    from jaxmm.reference import solve_ipopt  # the reference extra (casadi, adam-robotics)

    task = tasks.scenario(args.scenario, knots=args.knots, keep_horizon=True)
    ours = our_iterations(task, args.iterations)
    with tempfile.TemporaryDirectory() as folder:
        urdf, log_file = os.path.join(folder, "robot.urdf"), os.path.join(folder, "ipopt.log")
        with open(urdf, "wb") as handle:
            handle.write(jaxmm.assemble_urdf(jaxmm.robots.ironcub_description()).write_xml_string())
        solve_ipopt(task, urdf, tasks.initial_guess(task), tol=1e-4, max_iter=args.iterations,
                    options=dict(bound_relax_factor=0.0, output_file=log_file, file_print_level=5))
        with open(log_file) as handle:
            theirs = ipopt_iterations(handle.read())

    rows, parted = [], None
    for (iteration, restoration, objective, violation, regularisation, alpha), row in zip(theirs, ours):
        difference = abs(row[0] - objective) / max(abs(objective), 1e-300)
        if parted is None and difference > args.part:
            parted = iteration
        delta_w = f"{math.log10(row[5]):.2f}" if row[5] > 0 else "-"
        rows.append((f"{iteration}{'r' if restoration else ''}", f"{objective:.7e}", f"{row[0]:.7e}", f"{difference:.1e}",
                     f"{violation:.2e}", f"{row[1]:.2e}", regularisation, delta_w, alpha, f"{row[4]:.2e}"))
    print("\n".join(machine_lines(("jax", "jaxlib", "numpy", "casadi", "adam-robotics"))))
    print(f"{args.scenario} N = {args.knots} (published horizon), from the published guess; IPOPT with bound_relax_factor 0\n")
    print(render(("iteration", "IPOPT objective", "ours", "relative difference", "IPOPT inf_pr", "our violation",
                  "IPOPT lg(rg)", "our lg(δ_w)", "IPOPT α", "our α"), rows))
    print(f"\nThe paths part (objectives differ by more than {args.part:g}) at iteration "
          f"{parted if parted is not None else 'none of the ' + str(len(rows))}.")


if __name__ == "__main__":
    main()
