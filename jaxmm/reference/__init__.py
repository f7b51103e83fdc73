"""An independent CasADi transcription of the NLP of docs/formulation.md, with kinematics from
ADAM's CasADi backend and an IPOPT solve: the reference the JAX transcription is checked
against.

Needs the ``reference`` extra (casadi, adam-robotics with its CasADi backend, which imports
liecasadi). jaxmm itself never imports this subpackage.
"""

from jaxmm.reference.casadi_nlp import (
    COST_TERMS,
    PATH_EQUALITIES,
    PATH_INEQUALITIES,
    TRANSITION_EQUALITIES,
    TRANSITION_INEQUALITIES,
    ReferenceNLP,
    solve_ipopt,
)

__all__ = [
    "COST_TERMS",
    "PATH_EQUALITIES",
    "PATH_INEQUALITIES",
    "TRANSITION_EQUALITIES",
    "TRANSITION_INEQUALITIES",
    "ReferenceNLP",
    "solve_ipopt",
]
