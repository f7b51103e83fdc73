"""Analysis of a planned trajectory: ``validate`` checks it against the physics (``validation``),
``plots`` draws its figures and ``animation`` its motion."""

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

__all__ = ["Check", "ValidationReport", "airborne_corners", "check_trajectory", "complementarity", "corner_groups",
           "flight_knots", "resimulate_com", "validate"]
