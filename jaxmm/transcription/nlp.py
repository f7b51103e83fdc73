"""The task as a stage-wise NLP over scaled flat knot vectors z̃ = z / d (docs/formulation.md).

The functions below are module-level, so the ``StagewiseFunctions`` they form is one hashable
static object: every task of the same structure reuses the same compiled code.
"""

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.centroidal import centroidal_kinematics_curvature
from jaxmm.transcription import constraints, costs
from jaxmm.transcription.stagewise import StagewiseFunctions, StagewiseNLP
from jaxmm.transcription.variables import Trajectory


def _knot(task, z):
    layout = task.layout
    return layout.unflatten(z * layout.scale())


def _concat(values, names):
    return jnp.concatenate([jnp.reshape(values[name], (-1,)) for name in names])


def _knot_cost(task, z, theta, role):
    return costs.knot_cost(task, task.weights, _knot(task, z), theta[0], role)


def _global_cost(task, theta):
    return task.weights.horizon * theta[0]


def _path_equality(task, z, theta):
    return _concat(constraints.path_equalities(task, _knot(task, z), theta[0]), constraints.PATH_EQUALITIES)


def _transition_equality(task, z, z_next, theta):
    values = constraints.transition_equalities(task, _knot(task, z), _knot(task, z_next), theta[0])
    return _concat(values, constraints.TRANSITION_EQUALITIES)


def _path_inequality(task, z, theta):
    return _concat(constraints.path_inequalities(task, _knot(task, z), theta[0]), constraints.PATH_INEQUALITIES)


def _path_hessian(task, z, theta, y_equality, y_inequality):
    """Hessian of y_e·e + y_g·g w.r.t. (z̃, θ), exact, by the chain rule through the kinematics κ(q):
    ``jax.hessian`` of the constraints with κ linearised at q (cheap algebra), plus Σ w ∇²κ with
    w = ∂(y·c)/∂κ, where only q's n_q tangents traverse the kinematics (``jax.hessian`` of the whole
    knot would push all nz + ng of them through it)."""
    nz = z.shape[0]
    robot = task.robot

    def configuration(z):
        return _knot(task, z).configuration

    def weighted(w, kinematics):
        knot, total_time = _knot(task, w[:nz]), w[nz]
        equalities = constraints.path_equalities(task, knot, total_time, kinematics)
        inequalities = constraints.path_inequalities(task, knot, total_time, kinematics)
        return jnp.dot(y_equality, _concat(equalities, constraints.PATH_EQUALITIES)) + jnp.dot(
            y_inequality, _concat(inequalities, constraints.PATH_INEQUALITIES)
        )

    q0 = configuration(z)
    kin0 = constraints.knot_kinematics(task, q0)
    jacobian = jax.jacfwd(constraints.knot_kinematics, argnums=1)(task, q0)

    def linearised(w):
        dq = configuration(w[:nz]) - q0
        return weighted(w, jax.tree.map(lambda k, J: k + J @ dq, kin0, jacobian))

    w0 = jnp.concatenate([z, theta])
    hessian = jax.hessian(linearised)(w0)
    weights = jax.grad(weighted, argnums=1)(w0, kin0)
    curvature = centroidal_kinematics_curvature(
        robot.model, q0, robot.contact_frames + robot.jet_frames, weights
    )
    selection = jax.jacfwd(configuration)(z)  # q is linear in z̃
    return hessian.at[:nz, :nz].add(selection.T @ curvature @ selection)


def _transition_inequality(task, z, z_next, theta):
    values = constraints.transition_inequalities(task, _knot(task, z), _knot(task, z_next), theta[0])
    return _concat(values, constraints.TRANSITION_INEQUALITIES)


FUNCTIONS = StagewiseFunctions(
    knot_cost=_knot_cost,
    global_cost=_global_cost,
    path_equality=_path_equality,
    transition_equality=_transition_equality,
    path_inequality=_path_inequality,
    transition_inequality=_transition_inequality,
    path_hessian=_path_hessian,
)


def stagewise_nlp(task):
    """The task's NLP in the stage-wise format, over scaled variables (z̃ = z / d, θ = (T_total,))."""
    layout = task.layout
    scale = layout.scale()
    lower, upper = constraints.variable_bounds(task)
    bounds = constraints.inequality_bounds(task)
    path = [bounds[name] for name in constraints.PATH_INEQUALITIES]
    transition = [bounds[name] for name in constraints.TRANSITION_INEQUALITIES]
    return StagewiseNLP(
        args=task,
        knot_data=jnp.asarray(costs.knot_roles(task.n_knots)),
        z_lower=layout.flatten(lower.knots) / scale,
        z_upper=layout.flatten(upper.knots) / scale,
        theta_lower=jnp.reshape(lower.total_time, (1,)),
        theta_upper=jnp.reshape(upper.total_time, (1,)),
        path_lower=jnp.concatenate([b[0] for b in path]),
        path_upper=jnp.concatenate([b[1] for b in path]),
        transition_lower=jnp.concatenate([b[0] for b in transition]),
        transition_upper=jnp.concatenate([b[1] for b in transition]),
        functions=FUNCTIONS,
    )


def to_variables(task, trajectory):
    """Trajectory → scaled (Z (N + 1, nz), θ (1,))."""
    layout = task.layout
    return layout.flatten(trajectory.knots) / layout.scale(), jnp.reshape(trajectory.total_time, (1,))


def to_trajectory(task, Z, theta):
    """Scaled (Z, θ) → Trajectory (physical units)."""
    layout = task.layout
    return Trajectory(layout.unflatten(Z * layout.scale()), theta[0])


def family_rows(task):
    """{group: [(family, rows)]} for path/transition equalities and inequalities, in row order."""
    layout = task.layout
    n, nc, nj = layout.n_joints, layout.n_contacts, layout.n_jets
    sizes = dict(
        centroidal_dynamics=6, com=3, angular_momentum=3, contact_points=3 * nc, jet_dynamics=nj,
        com_integration=3, com_velocity_integration=3, angular_momentum_integration=3,
        base_position_integration=3, base_quaternion_integration=4, joint_integration=n,
        force_integration=3 * nc, thrust_integration=nj, thrust_rate_integration=nj,
        friction_cone=4 * nc, normal_complementarity=nc, corner_com=3 * nc, jet_com=3 * nj,
        planar_complementarity=4 * nc,
    )
    groups = dict(
        path_equality=constraints.PATH_EQUALITIES,
        transition_equality=constraints.TRANSITION_EQUALITIES,
        path_inequality=constraints.PATH_INEQUALITIES,
        transition_inequality=constraints.TRANSITION_INEQUALITIES,
    )
    return {group: [(name, sizes[name]) for name in names] for group, names in groups.items()}


def split_families(task, residuals):
    """Split a ``Residuals`` into {family: (knots, rows)} using ``family_rows``."""
    out = {}
    for group, families in family_rows(task).items():
        values = getattr(residuals, group)
        offsets = np.cumsum([0] + [rows for _, rows in families])
        for (name, _), start, stop in zip(families, offsets[:-1], offsets[1:]):
            out[name] = values[:, start:stop]
    return out
