"""Solving iRonCub tasks end to end with the interior-point solver.

Reduced scenarios with the published horizons (take-off: 14 knots of 0.25–0.5 s, the same
3.5–7 s as the published 70 knots, long enough for the jets to spin up; jumping: 15 knots of
0.2–0.4 s, the 3–6 s of the published 60) must converge and pass ``validate``, and IPOPT (the
CasADi reference) from the same guess must find no objective lower than ours by more than
``COMPARABLE`` at equal feasibility (both stop at a stationarity of 1e-4, so their objectives
differ at that level); an infeasible take-off must say so with finite numbers.
"""

import dataclasses
import logging

import jax
import numpy as np
import pytest

import jaxmm
from jaxmm import analysis, programs, solve, tasks
from jaxmm.solve import solve_task
from jaxmm.solver import interior_point as ip
from jaxmm.transcription import nlp as transcription

from conftest import REDUCED_TAKE_OFF

REDUCED_JUMPING = dict(knots=15, min_dt=0.2, max_dt=0.4)
COMPARABLE = 1e-3  # relative objective difference
FEASIBLE = 1e-6  # the violation our solves stop at (Options.tolerance, the NLP's own units)


@pytest.fixture(scope="module")
def take_off(solved_take_off):
    return solved_take_off


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


@pytest.mark.slow
def test_reduced_take_off_with_ipopt_slacks_reaches_the_same_optimum(take_off):
    """``Options(ipopt_slacks=True)`` (δ_w on the slacks too: IPOPT's treatment, with which
    take-off-and-landing needs fewer iterations) solves the reduced take-off to the default's
    optimum, and the answer passes ``validate``.
    Slow (``pytest -m slow``): with its compiled solve (a third in this worker) in the default
    run, the next test's compilation can fail with LLVM's "Cannot allocate memory" (the
    worker's memory mappings, see ``conftest.free_compiled_programs``)."""
    task, default = take_off
    options = dataclasses.replace(solve.DEFAULT_OPTIONS, ipopt_slacks=True)
    result = solve_task(task, options=options)
    assert result.status is ip.Status.CONVERGED, result.status.message
    assert analysis.validate(task, result.trajectory).ok
    assert float(result.solution.objective) == pytest.approx(float(default.solution.objective), rel=COMPARABLE)

def test_a_time_budget_stops_the_take_off_on_its_path(take_off):
    """A budget of 1 ms: the first iteration (not counted), then one slice of one iteration, then
    the solve stops with status TIME_LIMIT; its iterate is the one the full solve had there (the
    history rows agree) and every number is finite."""
    task, result = take_off
    stopped = solve_task(task, time_budget=1e-3)
    assert stopped.status is ip.Status.TIME_LIMIT, stopped.status.message
    count = int(stopped.solution.iterations)
    assert count == 2
    np.testing.assert_allclose(np.asarray(stopped.solution.history)[:count],
                               np.asarray(result.solution.history)[:count], rtol=1e-12)
    leaves = jax.tree.leaves((stopped.trajectory, stopped.solution.Z, stopped.violation_per_family))
    assert all(np.all(np.isfinite(np.asarray(leaf))) for leaf in leaves)


def _cross_check(task, result, tmp_path, comparable=COMPARABLE):
    """IPOPT from the same guess on the same robot, asked for our feasibility (``constr_viol_tol``
    1e-6): ours is at least as feasible as IPOPT's answer, and where IPOPT's is as feasible as
    ours, its objective is not lower than ours by more than ``comparable`` (relative). A lower
    IPOPT answer that is less feasible than ours is printed, not compared: a looser point can be
    cheaper."""
    from jaxmm.reference import solve_ipopt

    logging.getLogger("yourdfpy").setLevel(logging.ERROR)
    urdf = tmp_path / "ironcub.urdf"
    urdf.write_bytes(jaxmm.assemble_urdf(jaxmm.robots.ironcub_description()).write_xml_string())
    trajectory, info = solve_ipopt(task, urdf, tol=1e-4, options=dict(constr_viol_tol=FEASIBLE))
    nlp = transcription.stagewise_nlp(task)
    theirs_violation = float(ip.violation(nlp, *transcription.to_variables(task, trajectory))[0])
    ours_violation = float(result.solution.violation)
    ours, theirs = float(result.solution.objective), float(info["objective"])
    print(f"N = {task.n_intervals}: ours {ours:.8e} (violation {ours_violation:.1e}, "
          f"{int(result.solution.iterations)} iterations, {result.status.name}), IPOPT {theirs:.8e} "
          f"(violation {theirs_violation:.1e}, {info['iterations']} iterations, {info['status']})")
    assert theirs_violation <= 1e-4, f"IPOPT's answer is not feasible ({theirs_violation:.1e}): nothing to compare"
    assert ours_violation <= max(theirs_violation, FEASIBLE)
    as_feasible = theirs_violation <= max(ours_violation, FEASIBLE)
    assert not (as_feasible and theirs < ours - comparable * abs(ours)), (
        f"IPOPT ({info['status']}) found an answer as feasible as ours and lower by "
        f"{(ours - theirs) / abs(ours):.2e} (relative): {theirs:.8e} against {ours:.8e}")


def test_ipopt_from_the_same_guess_finds_no_lower_take_off(take_off, tmp_path):
    _cross_check(*take_off, tmp_path)


@pytest.fixture(scope="module")
def jumping():
    task = tasks.scenario("jumping", **REDUCED_JUMPING)
    return task, solve_task(task)


def test_reduced_jumping_converges_and_passes_validate(jumping):
    task, result = jumping
    assert result.status is ip.Status.CONVERGED, result.status.message
    report = analysis.validate(task, result.trajectory)
    assert report.ok, str(report)
    assert report.flight_knots, str(report)  # it jumps


def test_ipopt_from_the_same_guess_finds_no_jump_lower_by_more_than_2e_3(jumping, tmp_path):
    """Ours converges to another local optimum of the relaxed complementarity than the feasible
    point where IPOPT stops (``Error_In_Step_Computation``), which is lower by a margin that
    depends on the machine's floating point: ours 6.2532e5–6.2542e5 against IPOPT's 6.24501e5
    (Intel Xeon, 1.3e-3 lower) and 6.25041e5 (AMD EPYC, 4.6e-4 lower). The comparison is the
    take-off's with 2e-3 for 1e-3."""
    _cross_check(*jumping, tmp_path, comparable=2e-3)


def test_an_infeasible_take_off_is_reported_with_finite_numbers():
    """The final CoM 5 m up with every jet capped at 1 N, in 14 steps of 0.01 s: the velocity
    bounds cannot move the CoM that far in 0.14 s. (With the 3.5–7 s horizon the same targets
    are feasible for the NLP: feet that push while airborne, paid for by complementarity slack.)
    The restoration phase minimises the violation before giving up: it spreads the gap of
    several metres over the 14 steps' integration rows (0.42 m on the worst one), so
    the stop is far above any tolerance, not at it. Steps cut to ≈ 1e-4 by the bounds would crawl
    there for thousands of iterations; short steps that no longer cut the violation start the
    restoration phase (``Options.max_short_steps``), so it ends within 1,000."""
    task = tasks.scenario("take_off", knots=14, min_dt=0.01, max_dt=0.01, final_com=(0.0, 0.0, 5.57),
                          max_thrust=(1.0, 1.0, 1.0, 1.0))
    result = solve_task(task)  # the default options: the same compiled solve as the take-off's
    assert result.status is ip.Status.INFEASIBLE, result.status.message
    assert int(result.solution.iterations) < 1000
    assert float(result.solution.violation) > 0.05
    leaves = jax.tree.leaves((result.trajectory, result.solution.Z, result.solution.multipliers))
    assert all(np.all(np.isfinite(np.asarray(leaf))) for leaf in leaves)
    assert np.isfinite(float(result.solution.objective))


def test_warm_start_from_the_solution_of_a_neighbouring_task(take_off):
    """A target 2 cm lower, started from the take-off's solution and multipliers, converges in
    fewer than half the iterations of a cold solve of that task, to an optimum as good to 1e-3.
    The task has two nearby local optima (5.11340e6 and 5.11431e6): one feasible for
    the NLP but not physical (with the CoM 2 cm lower, a corner 1 cm up keeps ≈ 6 N, paid for by
    ≈ 0.8 of complementarity slack; ``validate`` fails it), the other keeping the force off that
    corner; which one each solve reaches has changed with rounding-level changes of the solver,
    so only the warm start's constraint checks are required. Both run the iterations the
    take-off compiled."""
    _, cold = take_off
    neighbour = tasks.scenario("take_off", **REDUCED_TAKE_OFF, final_com=(0.0, 0.0, 0.78))
    compiled = programs.advance._cache_size()
    warm = solve_task(neighbour, warm_start=cold)
    reference = solve_task(neighbour)
    assert programs.advance._cache_size() == compiled, "the warm start compiled its own iterations"
    assert warm.status is ip.Status.CONVERGED, warm.status.message
    assert reference.status is ip.Status.CONVERGED, reference.status.message
    assert int(warm.solution.iterations) < int(reference.solution.iterations) / 2
    assert float(warm.solution.violation) <= 1e-6
    ours, theirs = float(warm.solution.objective), float(reference.solution.objective)
    assert abs(ours - theirs) <= 1e-3 * abs(theirs)
    warm_report = analysis.validate(neighbour, warm.trajectory)
    assert all(c.passed for c in warm_report.checks if c.name.startswith("constraint ")), str(warm_report)
    print(f"warm start: {int(warm.solution.iterations)} iterations, objective {ours:.8e} "
          f"(cold: {int(reference.solution.iterations)}, {theirs:.8e})")


def test_with_intervals_keeps_the_horizons_and_names_bad_counts():
    """``tasks.with_intervals`` of a published scenario is that scenario built with fewer knots
    and ``keep_horizon`` (every leaf equal); a count that is not an integer ≥ 2 is refused."""
    coarse = tasks.with_intervals(tasks.scenario("take_off"), REDUCED_TAKE_OFF["knots"])
    built = tasks.scenario("take_off", knots=REDUCED_TAKE_OFF["knots"], keep_horizon=True)
    assert coarse.n_intervals == built.n_intervals and jax.tree.structure(coarse) == jax.tree.structure(built)
    for a, b in zip(jax.tree.leaves(coarse), jax.tree.leaves(built)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_allclose(float(coarse.params.max_dt) * 14, 0.1 * 70)
    for bad in (1, 2.5, True, "7"):
        with pytest.raises(ValueError, match="n_intervals must be an integer"):
            tasks.with_intervals(built, bad)

