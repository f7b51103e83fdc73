"""jaxmm: JAX-differentiable whole-body trajectory optimisation for multimodal robots.

Importing jaxmm enables float64 in JAX: every quantity of the library is double precision.
Conventions (q = (p, ρ xyzw, s), ν = (ṗ, ω world, ṡ)) are documented in ``jaxmm.model``.
"""

import jax

jax.config.update("jax_enable_x64", True)

from jaxmm import compilation, so3  # noqa: E402
from jaxmm.centroidal import (  # noqa: E402
    centroidal_momentum,
    centroidal_momentum_matrix,
    com_jacobian,
    com_position,
    total_mass,
)
from jaxmm.configuration import (  # noqa: E402
    configuration_derivative,
    integrate_configuration,
    make_configuration,
    neutral_configuration,
    split_configuration,
)
from jaxmm.kinematics import body_poses, frame_jacobian, frame_pose, frame_poses  # noqa: E402
from jaxmm.model import Model, Topology, UnknownNameError  # noqa: E402
from jaxmm.robots import Robot, assemble_urdf, load_ironcub, load_robot  # noqa: E402
from jaxmm.urdf import URDFError, model_from_urdf, read_urdf  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "Model",
    "Robot",
    "Topology",
    "URDFError",
    "UnknownNameError",
    "assemble_urdf",
    "body_poses",
    "centroidal_momentum",
    "centroidal_momentum_matrix",
    "com_jacobian",
    "com_position",
    "compilation",
    "configuration_derivative",
    "frame_jacobian",
    "frame_pose",
    "frame_poses",
    "integrate_configuration",
    "load_ironcub",
    "load_robot",
    "make_configuration",
    "model_from_urdf",
    "neutral_configuration",
    "read_urdf",
    "so3",
    "split_configuration",
    "total_mass",
]
