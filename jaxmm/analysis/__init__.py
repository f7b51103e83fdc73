"""Analysis of a planned trajectory: ``validate`` checks it against the physics (``validation``),
``joint_torques`` computes the torques it needs (``torques``), ``plots`` draws its figures and
``animation`` its motion."""

from jaxmm.analysis.torques import TorqueReport, joint_torques, knot_accelerations

from jaxmm.analysis.validation import (
    Check,
    ValidationReport,
    airborne_corners,
    check_trajectory,
    complementarity,
    corner_groups,
    flight_knots,
    resimulate_com,
    validate,
)

__all__ = ["Check", "TorqueReport", "ValidationReport", "airborne_corners", "check_trajectory", "complementarity",
           "corner_groups", "flight_knots", "joint_torques", "knot_accelerations", "resimulate_com", "validate"]
