"""``CONVERGED`` means physical: a solve that reports ``CONVERGED`` gives a trajectory that passes
``validate`` (the constraints in physical units, no force on a corner off the ground, the CoM
re-simulated from the forces and thrusts).

The published scenarios at reduced size (take-off and jumping: ``test_solve_task``) and variants
a user would try: other targets and horizons of the same 14-knot take-off (one compiled solve
serves them all: targets and time steps are data) and a longer jump. Some variants converge to a
point of the published NLP where a corner 1–3 cm above the ground still pushes: the relaxed
complementarity f_z c_z ≤ ε_n (eq. 20) is paid for with slack there. They are marked
as expected failures (strict: one that starts to pass fails the run, so that the mark goes).
Scholtes' relaxation without slacks (``tasks.exact_complementarity``), warm-started from such an
answer, moves it to a physical one; so does the elastic-mode continuation (``solve_elastic``),
from the published guess.
"""

import numpy as np
import pytest

from jaxmm import analysis, programs, tasks
from jaxmm.transcription import costs
from jaxmm.solve import DEFAULT_OPTIONS, solve_elastic, solve_task
from jaxmm.solver import interior_point as ip

from conftest import REDUCED_TAKE_OFF

UP = dict(REDUCED_TAKE_OFF, final_com=(0.0, 0.0, 0.95))
SIGMA = 1e-6  # [N m]: at most 1e-4 N on a corner 1 cm up
_SOLVED = {}  # (name, overrides) → (task, TaskSolution): the published NLP solved once per case


def _solved(name, overrides):
    key = (name, tuple(sorted(overrides.items())))
    if key not in _SOLVED:
        task = tasks.scenario(name, **overrides)
        _SOLVED[key] = task, solve_task(task)
    return _SOLVED[key]


# Expected failures, strict: these variants converge to an unphysical optimum of the published NLP
# (measured: 7.2 N, 28 N and 28 N on corners above 1 cm), which ``solve_task`` solves as published;
# ``solve_elastic`` makes them physical (below), and a strict mark turns red if the NLP changes.
PUSHES_IN_THE_AIR = pytest.mark.xfail(
    strict=True, reason="the relaxed contact complementarity lets a corner off the ground push (paid for with slack)")

CASES = [
    pytest.param("take_off", dict(REDUCED_TAKE_OFF, final_com=(-0.3, 0.0, 0.80)), id="take-off 30 cm forward"),
    pytest.param("take_off", UP, id="take-off 38 cm up",
                 marks=PUSHES_IN_THE_AIR),
    pytest.param("take_off", dict(REDUCED_TAKE_OFF, final_com=(0.0, 0.2, 0.75)), id="take-off 20 cm sideways",
                 marks=PUSHES_IN_THE_AIR),
    pytest.param("take_off", dict(knots=14, min_dt=0.15, max_dt=0.3), id="take-off in 2.1-4.2 s",
                 marks=PUSHES_IN_THE_AIR),
    pytest.param("jumping", dict(knots=15, min_dt=0.2, max_dt=0.4, final_com=(-0.3, 0.0, 0.57)),
                 id="jump 30 cm forward"),
]


@pytest.mark.parametrize("name, overrides", CASES)
def test_a_converged_answer_passes_validate(name, overrides):
    task, result = _solved(name, overrides)
    assert result.status is ip.Status.CONVERGED, result.status.message
    report = analysis.validate(task, result.trajectory)
    assert report.ok, str(report)


def test_exact_complementarity_from_the_published_answer_is_physical():
    """The take-off 38 cm up, whose published optimum pushes with a corner in the air, re-solved
    with f_z c_z ≤ σ_n, |f_z Δc| ≤ σ_t and no slack from that optimum: it converges, every normal
    product is within σ_n, the slacks are zero, and ``validate`` passes."""
    task, relaxed = _solved("take_off", UP)
    exact = tasks.exact_complementarity(task, SIGMA)
    result = solve_task(exact, warm_start=relaxed)
    assert result.status is ip.Status.CONVERGED, result.status.message
    knots = result.trajectory.knots
    normal = np.asarray(knots.contact_forces)[..., 2::3] * np.asarray(knots.contact_points)[..., 2::3]
    assert normal.max() <= SIGMA * (1 + 1e-6)
    assert np.all(np.asarray(knots.normal_slack) == 0) and np.all(np.asarray(knots.tangential_slack) == 0)
    report = analysis.validate(exact, result.trajectory)  # its own rows: the planar ones within σ_t
    assert report.ok, str(report)


def test_the_relaxation_homotopy_finds_a_lower_exact_optimum_from_the_published_guess():
    """The exact task (f_z c_z ≤ σ_n, |f_z Δc| ≤ σ_t, no slack) of the take-off 38 cm up, from
    the published guess: without the relaxation homotopy it converges to a physical answer above
    the one warm-started from the published optimum; with it (``programs.EXACT_OPTIONS``) it
    converges on the same exact task at least 5 % lower (measured: 114 iterations, 5.4251e6,
    against 922 iterations, 5.8439e6):
    every product within its σ (to the solver's violation tolerance), slack-free and physical."""
    task = tasks.exact_complementarity(tasks.scenario("take_off", **UP), SIGMA)
    alone = solve_task(task)
    assert alone.status is ip.Status.CONVERGED, alone.status.message
    homotopy = solve_task(task, options=programs.EXACT_OPTIONS)
    _exact_answer_is_physical(task, homotopy)
    assert float(homotopy.solution.objective) <= 0.95 * float(alone.solution.objective)


def _exact_answer_is_physical(task, result):
    """``result`` of the exact ``task`` converged, every normal product within σ_n and planar one
    within σ_t (to the solver's violation tolerance), no slack, and ``validate`` passes."""
    assert result.status is ip.Status.CONVERGED, result.status.message
    assert float(result.solution.violation) <= DEFAULT_OPTIONS.tolerance
    measure, params = analysis.complementarity(result.trajectory), task.params
    assert measure["normal"] <= float(params.complementarity_tolerance) + DEFAULT_OPTIONS.tolerance
    assert measure["planar"] <= float(params.planar_tolerance) + DEFAULT_OPTIONS.tolerance and measure["slack"] == 0
    report = analysis.validate(task, result.trajectory)
    assert report.ok, str(report)


def _exact_and_physical(task, answer):
    assert answer.status is ip.Status.CONVERGED, answer.status.message
    measure = analysis.complementarity(answer.result.trajectory)
    assert max(measure["normal"], measure["planar"]) == answer.products[-1] <= SIGMA
    assert float(answer.task.weights.complementarity_slack) == answer.weights[-1]
    report = analysis.validate(answer.task, answer.result.trajectory)
    assert report.ok, str(report)


def test_the_elastic_continuation_is_physical_where_the_published_optimum_is_not():
    """The take-off 38 cm up, whose published optimum pushes with a corner in the air, solved by
    ``solve_elastic`` from the published guess: the slack weight is raised until every
    complementarity product is within tolerance, the last stage converged, and ``validate``
    passes (the expected failure above, without a second formulation)."""
    answer = solve_elastic(tasks.scenario("take_off", **UP), tolerance=SIGMA)
    assert len(answer.iterations) >= 2 and answer.products[0] > SIGMA  # the published stage alone is not exact
    assert answer.weights[-1] > answer.weights[0]
    _exact_and_physical(answer.task, answer)


# Tasks other than the published four, none tuned: measured with the tests' XLA flags, stages
# (iterations) 175 + 189 + 1009 + 884 + 93 sideways, 206 + 159 + 108 + 68 in the short horizon,
# 269 + 60 + 67 + 22 forward, 243 + 78 + 44 + 331 backward, 144 + 68 + 105 + 29 at 20 knots; the
# jumps need no raise (192 and 191). With 38 cm up above, eight variants.
VARIANTS = [
    pytest.param("take_off", dict(REDUCED_TAKE_OFF, final_com=(0.0, 0.2, 0.75)), id="take-off 20 cm sideways"),
    pytest.param("take_off", dict(knots=14, min_dt=0.15, max_dt=0.3), id="take-off in 2.1-4.2 s"),
    pytest.param("take_off", dict(REDUCED_TAKE_OFF, final_com=(-0.3, 0.0, 0.80)), id="take-off 30 cm forward"),
    pytest.param("take_off", dict(REDUCED_TAKE_OFF, final_com=(0.2, 0.0, 0.80)), id="take-off 20 cm backward"),
    pytest.param("take_off", dict(knots=20, keep_horizon=True, final_com=(0.0, 0.0, 0.85)), id="take-off N = 20"),
    pytest.param("jumping", dict(knots=15, min_dt=0.2, max_dt=0.4, final_com=(-0.3, 0.0, 0.57)), id="jump 30 cm forward"),
    pytest.param("jumping", dict(knots=15, min_dt=0.2, max_dt=0.4, mid_com_height=0.65), id="jump to 0.65 m"),
]


@pytest.mark.slow
@pytest.mark.parametrize("name, overrides", VARIANTS)
def test_the_elastic_continuation_is_exact_and_physical_on_other_tasks(name, overrides):
    task = tasks.scenario(name, **overrides)
    _exact_and_physical(task, solve_elastic(task, tolerance=SIGMA))


# The exact task of the same variants, each solved once from the published guess with the
# homotopy (``programs.EXACT_OPTIONS``), none tuned (with the take-off 38 cm up above, eight):
# measured with the tests' XLA flags, 110 iterations sideways, 251 in the short horizon, 187
# forward, 220 backward, 301 at 20 knots, 74 and 67 for the jumps (114 for 38 cm up); 1,210 in all
# against the continuation's 4,734.
@pytest.mark.slow
@pytest.mark.parametrize("name, overrides", VARIANTS)
def test_the_relaxation_homotopy_solves_other_exact_tasks_to_physical_answers(name, overrides):
    task = tasks.exact_complementarity(tasks.scenario(name, **overrides), SIGMA)
    _exact_answer_is_physical(task, solve_task(task, options=programs.EXACT_OPTIONS))


def test_the_smooth_start_hands_the_squared_answer_to_the_published_penalty():
    """``solve_elastic(smooth_start=True)`` on the reduced take-off: a converged stage on Σ ε²
    (the squared penalty, with the task's slack weight), then the published ℓ1 stage from its
    answer and the raises, to an exact and physical answer whose published cost is within 0.1 %
    of the published NLP's optimum from the published guess."""
    task = tasks.scenario("take_off", **REDUCED_TAKE_OFF)
    answer = solve_elastic(task, tolerance=SIGMA, smooth_start=True)
    assert answer.penalties[:2] == ("squared", "linear") and set(answer.penalties[1:]) == {"linear"}
    assert answer.statuses[0] is ip.Status.CONVERGED
    assert answer.weights[0] == answer.weights[1] == float(task.weights.complementarity_slack)
    _exact_and_physical(task, answer)
    _, plain = _solved("take_off", REDUCED_TAKE_OFF)
    published = [float(costs.total_cost(task, r.trajectory)) for r in (answer.result, plain)]
    assert abs(published[0] - published[1]) <= 1e-3 * published[1], published


def test_a_smooth_start_that_does_not_converge_leaves_the_published_solve_as_it_was():
    """A smooth stage capped at 3 iterations does not converge: the published stage then starts
    from the guess with the given options, and its answer is ``solve_task``'s, bit for bit."""
    task, plain = _solved("take_off", REDUCED_TAKE_OFF)
    answer = solve_elastic(task, smooth_start=True, smooth_iterations=3, max_stages=0)
    assert [s.name for s in answer.statuses] == ["MAX_ITERATIONS", "CONVERGED"] and answer.iterations[0] == 3
    assert np.isnan(answer.products[0]) and answer.penalties == ("squared", "linear")
    assert answer.iterations[1] == int(plain.solution.iterations)
    np.testing.assert_array_equal(np.asarray(answer.result.solution.Z), np.asarray(plain.solution.Z))


def test_an_elastic_stage_that_does_not_converge_ends_the_continuation():
    """A raise capped at 3 iterations cannot converge: the answer is the published stage's, with
    the failed stage recorded and its product NaN."""
    task = tasks.scenario("take_off", **UP)
    answer = solve_elastic(task, tolerance=SIGMA, stage_iterations=3)
    assert [s.name for s in answer.statuses] == ["CONVERGED", "MAX_ITERATIONS"] and answer.iterations[1] == 3
    assert answer.products[0] > SIGMA and np.isnan(answer.products[1])
    assert answer.status is ip.Status.CONVERGED and answer.task is task
    assert answer.total_iterations == int(answer.result.solution.iterations) + 3
