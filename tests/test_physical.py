"""``CONVERGED`` means physical: a solve that reports ``CONVERGED`` gives a trajectory that passes
``validate`` (the constraints in physical units, no force on a corner off the ground, the CoM
re-simulated from the forces and thrusts).

The published scenarios at reduced size (take-off and jumping: ``test_solve_task``) and variants
a user would try: other targets and horizons of the same 14-knot take-off (one compiled solve
serves them all: targets and time steps are data) and a longer jump. Some variants converge to a
point of the published NLP where a corner 1–3 cm above the ground still pushes: the relaxed
complementarity f_z c_z ≤ ε_n (eq. 20) is paid for with slack there. They are marked
as expected failures (strict: one that starts to pass fails the run, so that the mark goes).
"""

import pytest

from jaxmm import analysis, tasks
from jaxmm.solve import solve_task
from jaxmm.solver import interior_point as ip

from conftest import REDUCED_TAKE_OFF

PUSHES_IN_THE_AIR = pytest.mark.xfail(
    strict=True, reason="the relaxed contact complementarity lets a corner off the ground push (paid for with slack)")

CASES = [
    pytest.param("take_off", dict(REDUCED_TAKE_OFF, final_com=(-0.3, 0.0, 0.80)), id="take-off 30 cm forward"),
    pytest.param("take_off", dict(REDUCED_TAKE_OFF, final_com=(0.0, 0.0, 0.95)), id="take-off 38 cm up",
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
    task = tasks.scenario(name, **overrides)
    result = solve_task(task)
    assert result.status is ip.Status.CONVERGED, result.status.message
    report = analysis.validate(task, result.trajectory)
    assert report.ok, str(report)
