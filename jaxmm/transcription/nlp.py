"""The task as a stage-wise NLP over scaled flat knot vectors z̃ = z / d (docs/formulation.md).

The functions below are module-level, so the ``StagewiseFunctions`` they form is one hashable
static object: every task of the same structure reuses the same compiled code.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.rigid_body.centroidal_derivatives import centroidal_kinematics_curvature, centroidal_kinematics_derivatives
from jaxmm.transcription import constraints, costs
from jaxmm.stagewise import KnotHessian, RowSupport, StagewiseFunctions, StagewiseNLP
from jaxmm.transcription.variables import Trajectory


def _knot(task, z):
    layout = task.layout
    return layout.unflatten(z * layout.scale())


def _concat(values, names):
    return jnp.concatenate([jnp.reshape(values[name], (-1,)) for name in names])


def _knot_cost(task, z, theta, role):
    return costs.knot_cost(task, task.weights, _knot(task, z), theta[0], role)


def _knot_cost_derivatives(task, z, theta, role):
    """Gradient (∂/∂z̃, ∂/∂θ) and Hessian blocks (∂²/∂z̃², ∂²/∂z̃∂θ, ∂²/∂θ²) of one knot's cost,
    exact, from one forward-over-reverse pass. The cost (eq. 32) is a weighted sum of squares of
    single entries of z̃ (a diagonal Hessian, read off one Hessian-vector product with ones) but
    for the base quaternion's SO(3) log at knot 0 (4 tangents) and T_total, which multiplies the
    running terms (ng tangents): 5 + ng tangents, the gradient their shared primal. ∂²/∂z̃² is
    returned as what it is, a ``KnotHessian``: that diagonal and the quaternion's 4 × 4 block."""
    nz = z.shape[0]
    quaternion = np.asarray(_columns(task.layout, "base_quaternion"))
    squares = np.setdiff1d(np.arange(nz), quaternion)
    w0 = jnp.concatenate([z, theta])
    ng = theta.shape[0]
    tangents = np.zeros((1 + quaternion.size + ng, nz + ng))
    tangents[0, squares] = 1.0
    tangents[1 + np.arange(quaternion.size), quaternion] = 1.0
    tangents[1 + quaternion.size + np.arange(ng), nz + np.arange(ng)] = 1.0

    def cost(w):
        return _knot_cost(task, w[:nz], w[nz:], role)

    gradient, products = jax.vmap(lambda e: jax.jvp(jax.grad(cost), (w0,), (e,)), out_axes=(None, 0))(
        jnp.asarray(tangents, w0.dtype))
    diagonal, rotation, globals_ = products[0], products[1:1 + quaternion.size], products[1 + quaternion.size:]
    zz = KnotHessian(jnp.zeros(nz, w0.dtype).at[squares].set(diagonal[squares]),
                     rotation[:, quaternion], tuple(int(c) for c in quaternion))
    return (gradient[:nz], gradient[nz:]), (zz, globals_[:, :nz].T, globals_[:, nz:])


def _global_cost(task, theta):
    return task.weights.horizon * theta[0]


def _path_equality(task, z, theta):
    return _concat(constraints.path_equalities(task, _knot(task, z), theta[0]), constraints.PATH_EQUALITIES)


def _transition_equality(task, z, z_next, theta):
    values = constraints.transition_equalities(task, _knot(task, z), _knot(task, z_next), theta[0])
    return _concat(values, constraints.TRANSITION_EQUALITIES)


def _path_inequality(task, z, theta):
    return _concat(constraints.path_inequalities(task, _knot(task, z), theta[0]), constraints.PATH_INEQUALITIES)


def _configuration(task, z):
    return _knot(task, z).configuration


def _kinematics_at(task, z):
    """(the kinematics κ at q(z̃), their Jacobian ∂κ/∂q): what both path derivatives need."""
    q0 = _configuration(task, z)
    return constraints.knot_kinematics(task, q0), jax.jacfwd(constraints.knot_kinematics, argnums=1)(task, q0)


def _kinematics_with_curvature(task, z, theta, y_equality, y_inequality):
    """(κ, ∂κ/∂q, Σ w ∇²κ) at z̃ with w = ∂(y·c)/∂κ, the Jacobian and the curvature from one pass
    (``centroidal_kinematics_derivatives``): what ``_path_hessian`` needs at these multipliers."""
    robot = task.robot
    q0 = _configuration(task, z)
    w0 = jnp.concatenate([z, theta])
    weights = jax.grad(_weighted_rows(task, y_equality, y_inequality), argnums=1)(
        w0, constraints.knot_kinematics(task, q0))
    return centroidal_kinematics_derivatives(robot.model, q0, robot.contact_frames + robot.jet_frames, weights)


def _weighted_rows(task, y_equality, y_inequality):
    """(w, kinematics) ↦ y_e·e + y_g·g at w = (z̃, θ) for the given kinematics."""
    def weighted(w, kinematics):
        e, g = _path_rows(task, w, kinematics)
        return jnp.dot(y_equality, e) + jnp.dot(y_inequality, g)

    return weighted


def _linearised(task, z, linearisation, fn):
    """fn(w, kinematics) as a function of w = (z̃', θ) with the kinematics linearised at z̃:
    κ + ∂κ/∂q (q(z̃') − q(z̃)). Its first derivatives at (z̃, θ) are fn's exact ones."""
    kin0, jacobian = linearisation[:2]
    q0 = _configuration(task, z)

    def at(w):
        dq = _configuration(task, w[: z.shape[0]]) - q0
        return fn(w, jax.tree.map(lambda k, J: k + J @ dq, kin0, jacobian))

    return at


def _path_rows(task, w, kinematics):
    """(e, g) at w = (z̃, θ) (θ = (T_total,)) for the given kinematics."""
    knot, total_time = _knot(task, w[:-1]), w[-1]
    return (_concat(constraints.path_equalities(task, knot, total_time, kinematics), constraints.PATH_EQUALITIES),
            _concat(constraints.path_inequalities(task, knot, total_time, kinematics), constraints.PATH_INEQUALITIES))


def _path_jacobian(task, z, theta, y_equality=None, y_inequality=None):
    """Both path functions' Jacobians w.r.t. (z̃, θ) by the chain rule through the kinematics'
    Jacobian (computed once, and returned for ``_path_hessian`` to reuse): the rows'
    explicit derivatives with κ held fixed (cheap algebra, nz + ng tangents), plus, in q's
    columns alone, their derivatives through κ (n_q tangents through the linearised
    kinematics): ((e_z, e_θ), (g_z, g_θ), (κ, ∂κ/∂q)). Given the path multipliers, the
    kinematics' curvature at them comes from the same pass as their Jacobian and is returned
    too, (κ, ∂κ/∂q, Σ w ∇²κ), for ``_path_hessian`` at those multipliers."""
    nz = z.shape[0]
    linearisation = (_kinematics_at(task, z) if y_equality is None
                     else _kinematics_with_curvature(task, z, theta, y_equality, y_inequality))
    w0 = jnp.concatenate([z, theta])
    explicit = jax.jacfwd(lambda w: _path_rows(task, w, linearisation[0]))(w0)
    q = _configuration_columns(task.layout)
    through = jax.jacfwd(lambda v: _linearised(task, z, linearisation, lambda w, kin: _path_rows(task, w0, kin))(
        w0.at[q].set(v)))(w0[q])
    e, g = (a.at[:, q].add(b) for a, b in zip(explicit, through))
    return (e[:, :nz], e[:, nz:]), (g[:, :nz], g[:, nz:]), linearisation


def _path_hessian(task, z, theta, y_equality, y_inequality, linearisation=None):
    """Hessian of y_e·e + y_g·g w.r.t. (z̃, θ), exact, by the chain rule through the kinematics κ(q):
    ``jax.hessian`` of the constraints with κ linearised at q (cheap algebra), plus Σ w ∇²κ with
    w = ∂(y·c)/∂κ, where only q's n_q tangents traverse the kinematics (``jax.hessian`` of the whole
    knot would push all nz + ng of them through it). linearisation: (κ, ∂κ/∂q) at z̃ from
    ``_path_jacobian``, or (κ, ∂κ/∂q, Σ w ∇²κ) if it was given these multipliers (None: computed
    here)."""
    robot = task.robot
    linearisation = _kinematics_at(task, z) if linearisation is None else linearisation
    weighted = _weighted_rows(task, y_equality, y_inequality)
    w0 = jnp.concatenate([z, theta])
    if len(linearisation) == 3:
        curvature = linearisation[2]
    else:
        weights = jax.grad(weighted, argnums=1)(w0, linearisation[0])
        curvature = centroidal_kinematics_curvature(
            robot.model, _configuration(task, z), robot.contact_frames + robot.jet_frames, weights
        )
    # q = d_q z̃_q (the scaling of q's columns): the chain rule's Sᵀ ∇²κ S is scaled and added to
    # q's block (the dense (nz × n_q) products would cost more than the rest of the Hessian).
    q = _configuration_columns(task.layout)
    scale = task.layout.scale()[q]
    return _linearised_hessian(
        _linearised(task, z, linearisation, weighted), lambda w: weighted(w, linearisation[0]), w0,
        _path_curvature_columns(task.layout), q, curvature * scale[:, None] * scale[None, :])


def _columns(layout, field, entries=slice(None), offset=0):
    block = layout.slices()[field]
    return offset + np.arange(block.start, block.stop)[entries]


def _configuration_columns(layout):
    """Flat columns of z̃ that hold q = (p, ρ, s)."""
    return np.concatenate([_columns(layout, f) for f in ("base_position", "base_quaternion", "joint_positions")])


def _path_curvature_columns(layout):
    """Flat columns of z̃ in which the path rows, kinematics linearised, are not linear: CoM, q, ν,
    forces and corners (the momentum rate, eq. 8; CMM ν, eq. 15), the jets' T, Ṫ, u (eq. 23).
    The path rows do not depend on T_total."""
    fields = ("com", "base_position", "base_quaternion", "joint_positions", "base_linear_velocity",
              "base_angular_velocity", "joint_velocities", "contact_forces", "contact_points", "thrust",
              "thrust_rate", "throttle")
    return np.sort(np.concatenate([_columns(layout, f) for f in fields]))  # increasing, as _embedded takes them


def _transition_curvature_columns(task):
    """Flat columns of (z̃_k, z̃_{k+1}) in which the transition rows are not linear, T_total apart:
    ρ_k and ω_{k+1} (quaternion integration, eq. 25), f_z,k and the corners' x, y at k and k+1
    (planar complementarity, eq. 21). Every other row is linear but for Δt × a rate. With the
    joint torques, also ν_k and the orientation, joints, ν, contact forces and thrusts at k+1
    (the base position does not move a joint torque). A tuple (static), for
    ``StagewiseFunctions.transition_curvature_columns``."""
    layout = task.layout
    nz = layout.size
    planar = np.sort(np.concatenate([_columns(layout, "contact_points", slice(i, None, 3)) for i in (0, 1)]))
    columns = [
        _columns(layout, "base_quaternion"), _columns(layout, "contact_forces", slice(2, None, 3)), planar,
        _columns(layout, "base_angular_velocity", offset=nz), planar + nz,
    ]
    if task.joint_torque_limits:
        now_fields, next_fields = constraints.FAMILY_FIELDS[constraints.JOINT_TORQUE]
        columns += [_columns(layout, f) for f in now_fields]
        columns += [_columns(layout, f, offset=nz) for f in next_fields if f != "base_position"]
    return tuple(int(c) for c in np.unique(np.concatenate(columns)))


def _transition_through_columns(task):
    """With the joint torques, the transition curvature columns whose tangents the Hessian needs:
    ρ_k and ω_{k+1} (quaternion integration), f_z,k (planar complementarity), and the orientation,
    joints and ν at k+1 (the torques). The rows are jointly affine in the other curvature columns
    (the corners' x, y, ν_k, and the contact forces and thrusts at k+1, which enter the torques
    linearly), so their Hessian rows come by symmetry. None (every column a tangent) without the
    torques. A tuple (static), for ``StagewiseFunctions.transition_through_columns``."""
    if not task.joint_torque_limits:
        return None
    layout = task.layout
    nz = layout.size
    columns = [_columns(layout, "base_quaternion"), _columns(layout, "contact_forces", slice(2, None, 3))]
    columns += [_columns(layout, f, offset=nz) for f in (
        "base_quaternion", "joint_positions", "base_linear_velocity", "base_angular_velocity", "joint_velocities")]
    return tuple(int(c) for c in np.unique(np.concatenate(columns)))


def _embedded(block, columns, size):
    """The (c, c) ``block`` at the rows and columns ``columns`` (static, increasing) of a
    (size, size) zero matrix, from slices of it and zeros: XLA's CPU scatter into zeros is
    several times dearer for the path Hessian."""
    columns = np.asarray(columns)
    cuts = np.flatnonzero(np.diff(columns) != 1) + 1
    runs = [(int(r[0]), int(r[-1]) + 1) for r in np.split(columns, cuts) if r.size]

    def along(x, axis):
        pieces, at, used = [], 0, 0
        for start, stop in runs + [(size, size)]:
            if start > at:
                pieces.append(jnp.zeros(x.shape[:axis] + (start - at,) + x.shape[axis + 1:], x.dtype))
            if stop > start:
                pieces.append(jax.lax.slice_in_dim(x, used, used + stop - start, axis=axis))
            at, used = stop, used + stop - start
        return jnp.concatenate(pieces, axis=axis)

    return along(along(block, 0), 1)


def _linearised_hessian(fn, fixed, w0, columns, through, curvature):
    """Hessian of fn at w0 over ``columns`` (fn is linear in every other entry of w0), by forward
    over reverse, 16 tangents at a time (``jax.hessian``'s all at once ran 1.5–1.9× slower on a
    CPU for 122 tangents and 71 knots), plus ``curvature`` (t, t) in the block of ``through``,
    for fn(w) = φ(w, κ(w)) with κ affine in w[through] alone (``_linearised``) and fixed(w) =
    φ(w, κ(w0)): only the tangents of ``through`` (⊂ columns, consecutive among them) go through
    κ's products, which dominate (30 of iRonCub's 122 tangents); the Hessian among the other
    columns is fixed's, and their rows of ``through``'s columns come by symmetry."""
    columns, through = np.asarray(columns), np.asarray(through)
    inside = np.isin(columns, through)
    kinematic, other = np.flatnonzero(inside), np.flatnonzero(~inside)
    a, b = int(kinematic[0]), int(kinematic[-1]) + 1
    if b - a != kinematic.size:
        raise ValueError("the kinematic columns must be consecutive among the curvature columns")
    v0 = w0[columns]
    gradient = jax.grad(lambda v: fn(w0.at[columns].set(v)))
    tangents = jnp.eye(columns.size, dtype=w0.dtype)
    across = jax.lax.map(lambda e: jax.jvp(gradient, (v0,), (e,))[1], tangents[kinematic], batch_size=16)
    fixed_gradient = jax.grad(lambda v: fixed(w0.at[columns[other]].set(v)))
    among = jax.lax.map(lambda e: jax.jvp(fixed_gradient, (v0[other],), (e,))[1],
                        jnp.eye(other.size, dtype=w0.dtype), batch_size=16)
    inner = jnp.block([[among[:a, :a], across[:, :a].T, among[:a, a:]],
                       [across[:, :a], across[:, a:b] + curvature, across[:, b:]],
                       [among[a:, :a], across[:, b:].T, among[a:, a:]]])
    return _embedded(inner, columns, w0.shape[0])


def _transition_inequality(task, z, z_next, theta):
    values = constraints.transition_inequalities(task, _knot(task, z), _knot(task, z_next), theta[0])
    return _concat(values, constraints.transition_inequality_families(task))


def _transition_inequality_jacobian(task, z, z_next, theta):
    """With the joint torques, the transition inequalities' Jacobian with the torque rows
    differentiated along the columns they depend on alone (``constraints.FAMILY_FIELDS``: ν_k and
    q, ν, the contact forces and the thrusts at k+1, and θ), where ``jax.jacfwd`` of the whole
    function would take all 2 nz + 1 tangents through inverse dynamics. None without the torques."""
    if not task.joint_torque_limits:
        return None
    layout = task.layout
    plain = dataclasses.replace(task, joint_torque_limits=False)
    paper = jax.jacfwd(_transition_inequality, argnums=(1, 2, 3))(plain, z, z_next, theta)
    now_fields, next_fields = constraints.FAMILY_FIELDS[constraints.JOINT_TORQUE]
    now = np.concatenate([_columns(layout, f) for f in now_fields])
    following = np.concatenate([_columns(layout, f) for f in next_fields])

    def torques(v, v_next, th):
        knot, next_knot = _knot(task, z.at[now].set(v)), _knot(task, z_next.at[following].set(v_next))
        return constraints.transition_inequalities(task, knot, next_knot, th[0])[constraints.JOINT_TORQUE]

    t_now, t_next, t_theta = jax.jacfwd(torques, argnums=(0, 1, 2))(z[now], z_next[following], theta)
    rows = t_now.shape[0]
    t_z = jnp.zeros((rows, z.shape[0]), z.dtype).at[:, now].set(t_now)
    t_znext = jnp.zeros((rows, z.shape[0]), z.dtype).at[:, following].set(t_next)
    return tuple(jnp.concatenate([p, t]) for p, t in zip(paper, (t_z, t_znext, t_theta)))


def _row_supports(task):
    """{group: RowSupport per family}: the columns of z̃_k (and z̃_{k+1}) each family's rows can
    depend on (``constraints.FAMILY_FIELDS``), from the task's static layout."""
    layout = task.layout
    out = {}
    for group, families in family_rows(task).items():
        runs, start = [], 0
        for name, size in families:
            now, following = constraints.FAMILY_FIELDS[name]
            columns = [np.concatenate([_columns(layout, f) for f in fields]) if fields else np.zeros(0, int)
                       for fields in (now, following)]
            runs.append(RowSupport(start, start + size, *(tuple(int(c) for c in np.sort(x)) for x in columns)))
            start += size
        out[group] = tuple(runs)
    return out


FUNCTIONS = StagewiseFunctions(
    knot_cost=_knot_cost,
    knot_cost_derivatives=_knot_cost_derivatives,
    global_cost=_global_cost,
    path_equality=_path_equality,
    transition_equality=_transition_equality,
    path_inequality=_path_inequality,
    transition_inequality=_transition_inequality,
    path_hessian=_path_hessian,
    transition_curvature_columns=_transition_curvature_columns,
    transition_through_columns=_transition_through_columns,
    transition_inequality_jacobian=_transition_inequality_jacobian,
    row_supports=_row_supports,
    path_jacobian=_path_jacobian,
)


def _relaxation(bounds, names, planar_share):
    """Per row of the families ``names`` (their ``bounds``): the bound that the solver's
    relaxation homotopy widens and by how much of σ, +1 the upper, −1 the lower, on the
    complementarity rows of eq. (20, 21) only (Scholtes' relaxation, f_z c_z ≤ ε_n + σ), times
    ``planar_share`` (κ_t, ``TaskParams.planar_relaxation``) on the planar rows; 0 elsewhere."""
    share = dict(zip(constraints.COMPLEMENTARITY, (1.0, planar_share)))
    signs = [share[name] * jnp.where(jnp.isfinite(bounds[name][1]), 1.0, -1.0) if name in share
             else jnp.zeros_like(bounds[name][1]) for name in names]
    return jnp.concatenate(signs)


def stagewise_nlp(task):
    """The task's NLP in the stage-wise format, over scaled variables (z̃ = z / d, θ = (T_total,))."""
    layout = task.layout
    scale = layout.scale()
    lower, upper = constraints.variable_bounds(task)
    bounds = constraints.inequality_bounds(task)
    transition_families = constraints.transition_inequality_families(task)
    path = [bounds[name] for name in constraints.PATH_INEQUALITIES]
    transition = [bounds[name] for name in transition_families]
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
        path_relaxation=_relaxation(bounds, constraints.PATH_INEQUALITIES, task.params.planar_relaxation),
        transition_relaxation=_relaxation(bounds, transition_families, task.params.planar_relaxation),
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
        planar_complementarity=4 * nc, joint_torque=n,
    )
    groups = dict(
        path_equality=constraints.PATH_EQUALITIES,
        transition_equality=constraints.TRANSITION_EQUALITIES,
        path_inequality=constraints.PATH_INEQUALITIES,
        transition_inequality=constraints.transition_inequality_families(task),
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
