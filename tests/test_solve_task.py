"""Solving iRonCub tasks end to end with the interior-point solver.

A reduced take-off with the published horizon (14 knots of 0.25–0.5 s: the same 3.5–7 s as the
published 70 knots, long enough for the jets to spin up) must converge and pass ``validate``;
IPOPT (the CasADi reference) from the same guess must not find a lower objective; an
infeasible take-off must say so with finite numbers.
"""

import logging

import jax
import numpy as np
import pytest

import jaxmm
from jaxmm import analysis, tasks
from jaxmm.optimise import solve_task
from jaxmm.solver import interior_point as ip
from jaxmm.transcription import nlp as transcription

REDUCED_TAKE_OFF = dict(knots=14, min_dt=0.25, max_dt=0.5)


@pytest.fixture(scope="module")
def take_off():
    task = tasks.scenario("take_off", **REDUCED_TAKE_OFF)
    return task, solve_task(task)


def test_reduced_take_off_converges_and_passes_validate(take_off):
    task, result = take_off
    assert result.status is ip.Status.CONVERGED, result.status.message
    report = analysis.validate(task, result.trajectory)
    assert report.ok, str(report)
    assert float(result.solution.violation) <= 1e-6
    assert set(result.violation_per_family) == {c.name.removeprefix("constraint ") for c in report.checks
                                                if c.name.startswith("constraint ")}
    assert max(float(v) for v in result.violation_per_family.values()) <= 1e-6
    # It is a take-off: the last knots are airborne and the jets hold the weight there.
    assert report.flight_knots and report.flight_knots[-1] == task.n_knots - 1, str(report)
    weight = float(jaxmm.total_mass(task.robot.model)) * 9.81
    thrust = np.asarray(result.trajectory.knots.thrust)[-1].sum()
    assert 0.9 * weight < thrust < 1.1 * weight
    history = np.asarray(result.solution.history)[: int(result.solution.iterations)]
    assert np.all(np.isfinite(history)) and np.all(np.isnan(np.asarray(result.solution.history)[int(result.solution.iterations):]))


def test_ipopt_from_the_same_guess_finds_no_lower_objective(take_off, tmp_path):
    pytest.importorskip("casadi", reason="the IPOPT reference needs casadi (the 'reference' extra)")
    pytest.importorskip("adam.casadi", reason="the IPOPT reference needs adam-robotics[casadi]")
    from jaxmm.reference import solve_ipopt

    logging.getLogger("yourdfpy").setLevel(logging.ERROR)
    task, result = take_off
    urdf = tmp_path / "ironcub.urdf"
    urdf.write_bytes(jaxmm.assemble_urdf(jaxmm.robots.ironcub_description()).write_xml_string())
    trajectory, info = solve_ipopt(task, urdf, tol=1e-4)
    assert info["success"], info
    nlp = transcription.stagewise_nlp(task)
    ipopt_violation = float(ip.violation(nlp, *transcription.to_variables(task, trajectory))[0])
    ours, theirs = float(result.solution.objective), float(info["objective"])
    print(f"take-off N = 14: ours {ours:.8e} (violation {float(result.solution.violation):.1e}, "
          f"{int(result.solution.iterations)} iterations), IPOPT {theirs:.8e} (violation {ipopt_violation:.1e}, "
          f"{info['iterations']} iterations)")
    assert ours <= theirs * (1 + 1e-6)
    assert float(result.solution.violation) <= max(ipopt_violation, 1e-6)


def test_an_infeasible_take_off_is_reported_with_finite_numbers():
    """The final CoM 5 m up with every jet capped at 1 N, in 14 steps of 0.01 s: the velocity
    bounds cannot move the CoM that far in 0.14 s. (With the 3.5–7 s horizon the same targets
    are feasible for the NLP: feet that push while airborne, paid for by complementarity slack.)"""
    task = tasks.scenario("take_off", knots=14, min_dt=0.01, max_dt=0.01, final_com=(0.0, 0.0, 5.57),
                          max_thrust=(1.0, 1.0, 1.0, 1.0))
    result = solve_task(task, options=ip.Options(max_iterations=200))
    assert result.status is ip.Status.INFEASIBLE, result.status.message
    assert float(result.solution.violation) > 1.0
    leaves = jax.tree.leaves((result.trajectory, result.solution.Z, result.solution.multipliers))
    assert all(np.all(np.isfinite(np.asarray(leaf))) for leaf in leaves)
    assert np.isfinite(float(result.solution.objective))


def test_warm_start_from_the_solution_of_a_neighbouring_task(take_off):
    """A target 2 cm lower, started from the take-off's solution and multipliers."""
    _, cold = take_off
    neighbour = tasks.scenario("take_off", **REDUCED_TAKE_OFF, final_com=(0.0, 0.0, 0.78))
    warm = solve_task(neighbour, warm_start=cold)
    assert warm.status is ip.Status.CONVERGED, warm.status.message
    assert int(warm.solution.iterations) < int(cold.solution.iterations) / 2
    report = analysis.validate(neighbour, warm.trajectory)
    assert report.ok, str(report)
    print(f"warm start: {int(warm.solution.iterations)} iterations (cold: {int(cold.solution.iterations)})")
