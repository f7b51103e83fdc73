"""jaxmm: JAX-differentiable whole-body trajectory optimisation for multimodal robots.

The public API in one screen: load a robot (``load_robot``, ``load_ironcub``), its rigid-body
quantities (``frame_poses``, ``com_position``, ``centroidal_momentum_matrix``, ...), a task
(``scenario``, ``build_task``, ``initial_guess``), one way to solve it (``solve_task``; to exact
contact complementarity, ``solve_elastic``), one to solve many (``solve_batch``), one to
differentiate a found optimum (``gradient``), and its check against the physics (``validate``).
The layers beneath are subpackages: ``rigid_body``, ``robots``, ``physics``, ``stagewise``,
``transcription``, ``solver``, ``analysis``.

Importing jaxmm enables float64 in JAX: every quantity of the library is double precision.
Conventions (q = (p, ρ xyzw, s), ν = (ṗ, ω world, ṡ)) are documented in ``jaxmm.rigid_body.model``.
"""

import jax

jax.config.update("jax_enable_x64", True)

from jaxmm import compilation  # noqa: E402
from jaxmm.analysis import TorqueReport, ValidationReport, joint_torques, validate  # noqa: E402
from jaxmm.batch import sample_guesses, solve_batch, summarise  # noqa: E402
from jaxmm.rigid_body import so3  # noqa: E402
from jaxmm.rigid_body.centroidal import (  # noqa: E402
    centroidal_momentum,
    centroidal_momentum_matrix,
    com_jacobian,
    com_position,
    total_mass,
)
from jaxmm.rigid_body.configuration import (  # noqa: E402
    configuration_derivative,
    integrate_configuration,
    make_configuration,
    neutral_configuration,
    split_configuration,
)
from jaxmm.rigid_body.dynamics import bias_forces, inverse_dynamics, mass_matrix  # noqa: E402
from jaxmm.rigid_body.kinematics import body_poses, frame_jacobian, frame_pose, frame_poses  # noqa: E402
from jaxmm.rigid_body.model import Model, Topology, UnknownNameError  # noqa: E402
from jaxmm.rigid_body.urdf import URDFError, model_from_urdf, read_urdf  # noqa: E402
from jaxmm.robots import Frame, Robot, assemble_urdf, edit_urdf, load_ironcub, load_robot  # noqa: E402
from jaxmm.solve import ElasticSolution, TaskSolution, gradient, solve_elastic, solve_task  # noqa: E402
from jaxmm.tasks import SCENARIOS, build_task, initial_guess, scenario  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "ElasticSolution",
    "Frame",
    "Model",
    "Robot",
    "SCENARIOS",
    "TaskSolution",
    "Topology",
    "TorqueReport",
    "URDFError",
    "UnknownNameError",
    "ValidationReport",
    "assemble_urdf",
    "bias_forces",
    "body_poses",
    "build_task",
    "centroidal_momentum",
    "centroidal_momentum_matrix",
    "com_jacobian",
    "com_position",
    "compilation",
    "configuration_derivative",
    "edit_urdf",
    "frame_jacobian",
    "frame_pose",
    "frame_poses",
    "gradient",
    "initial_guess",
    "integrate_configuration",
    "joint_torques",
    "inverse_dynamics",
    "load_ironcub",
    "load_robot",
    "make_configuration",
    "mass_matrix",
    "model_from_urdf",
    "neutral_configuration",
    "read_urdf",
    "sample_guesses",
    "scenario",
    "so3",
    "solve_batch",
    "solve_elastic",
    "solve_task",
    "split_configuration",
    "summarise",
    "total_mass",
    "validate",
]
