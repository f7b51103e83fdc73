"""The joint torques that saved plans need, against the motors' effort limits.

For each solution file written by ``jaxmm solve`` (``solution.npz``, ``jaxmm.io``), the joint
torques along the plan by inverse dynamics (``jaxmm.analysis.joint_torques``: ν̇ by the
transcription's backward-Euler rule, the contact forces and the jets' thrusts as external
forces). Printed: one row per plan (the largest |τ|/τ_max with its joint, knot and torque, the
joints over their limits, the base residual that the centroidal plan leaves unbalanced), then the
largest |τ| of every joint with a finite effort limit below ``--limit-below`` (default 1,000 N m:
iRonCub's URDF gives the torso and arms a placeholder of 50,000 N m), one column per plan.

Usage: python tools/torques.py DIR/solution.npz [...] [--limit-below 1000]
"""

import argparse
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))

from machine import render  # noqa: E402


def plan_rows(reports):
    """One row per (label, task, TorqueReport)."""
    rows = []
    for label, task, report in reports:
        name, knot, torque, limit = report.worst
        over = ", ".join(f"{joint} ×{load:.2f} at {len(knots)} knots" for joint, (knots, load) in report.saturated.items())
        rows.append((label, task.n_intervals, f"{report.load.max():.3f}", f"{name}, knot {knot}: {torque:.1f} / {limit:g} N m",
                     over or "none", f"{np.linalg.norm(report.base_force, axis=1).max():.3g} N",
                     f"{np.linalg.norm(report.base_torque, axis=1).max():.3g} N m"))
    return rows


def joint_rows(reports, limit_below):
    """Per joint with an effort limit below ``limit_below``: the limit and each plan's largest |τ|
    with its ratio to the limit."""
    _, task, first = reports[0]
    rows = []
    for j, name in enumerate(first.joint_names):
        limit = first.effort_limits[j]
        if not limit < limit_below:
            continue
        cells = [f"{np.abs(r.torques[:, j]).max():.1f} ({np.abs(r.torques[:, j]).max() / limit:.2f})" for _, _, r in reports]
        rows.append((name, f"{limit:g}", *cells))
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("solutions", nargs="+", help="solution files of jaxmm solve (jaxmm.io)")
    parser.add_argument("--limit-below", type=float, default=1000.0, help="joints listed: effort limit below this [N m]")
    args = parser.parse_args(argv)

    from jaxmm import analysis, io

    reports = []
    for path in args.solutions:
        task, result = io.load(path)
        bounded = ", torques bounded" if task.joint_torque_limits else ""
        reports.append((f"{task.name} ({result.status.name.lower()}{bounded})", task,
                        analysis.joint_torques(task, result.trajectory)))
    print(render(("plan", "N", "largest |τ|/τ_max", "where", "over the limit", "base force ≤", "base torque ≤"),
                 plan_rows(reports)))
    print()
    print(render(("joint", "τ_max [N m]", *(label for label, _, _ in reports)), joint_rows(reports, args.limit_below)))
    print("\nper plan: the largest |τ| [N m] over the knots (its ratio to τ_max)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
