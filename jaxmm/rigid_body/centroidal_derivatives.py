"""First and second derivatives of the centroidal kinematics (CoM, eq. 15; CMM, eq. 4 and 16; the
contact and jet frames' poses) by recursions over the tree in spatial-vector algebra, instead of
automatic differentiation through the kinematics.

Conventions. A spatial motion is (ω, v), v the velocity of the point at the origin; a spatial
force is (n, f), n the moment about the origin (Featherstone, *Rigid Body Dynamics Algorithms*,
2008, ch. 2). Optimised joint k has the motion subspace S_k. If joint i is an ancestor of joint
k or k itself (i ⪯ k), ∂S_k/∂s_i = S_i × S_k; a body that joint i moves changes its spatial
inertia by S_i ×* I − I S_i × (the identities of Pinocchio's centroidal derivatives). Every
second derivative below then takes the form H_ik = a_i · b_k for i ⪯ k, a_i from joint i alone
and b_k a sum over the subtree of k: one product of (n, 6) matrices, where automatic
differentiation pushes one tangent per joint through the whole kinematics.

The base's orientation enters every output as one rotation R(ρ) of quantities computed with the
base at the origin (``_base_frame``), so the derivatives along the quaternion's 4 entries are
those of a small function of ρ, by automatic differentiation; the base position moves the
positions one to one and nothing else.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from jaxmm.rigid_body import so3
from jaxmm.rigid_body.centroidal import body_inertials_world, bundle_from_poses
from jaxmm.rigid_body.configuration import check_configuration
from jaxmm.rigid_body.kinematics import body_poses, joint_axes_world

_IDENTITY_BASE = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])


def _cross_motion(S, m):
    """S × m for spatial motions S, m (…, 6) (Featherstone's crm(S) m)."""
    w, v = S[..., :3], S[..., 3:]
    return jnp.concatenate([jnp.cross(w, m[..., :3]), jnp.cross(v, m[..., :3]) + jnp.cross(w, m[..., 3:])], -1)


def _cross_force(S, f):
    """S ×* f for a spatial motion S and a force f (…, 6) (crf(S) f, crf(S) = −crm(S)ᵀ)."""
    w, v = S[..., :3], S[..., 3:]
    return jnp.concatenate([jnp.cross(w, f[..., :3]) + jnp.cross(v, f[..., 3:]), jnp.cross(w, f[..., 3:])], -1)


def _spatial_inertia(mass, com, inertia):
    """Spatial inertias about the origin (k, 6, 6) of bodies of mass (k,) [kg], CoM (k, 3) [m] and
    rotational inertia about it (k, 3, 3) [kg m²]: [[I − m [c]×², m [c]×], [−m [c]×, m 1]]."""
    C = jax.vmap(so3.skew)(com)
    m = mass[:, None, None]
    eye = jnp.broadcast_to(jnp.eye(3, dtype=com.dtype), C.shape)
    return jnp.concatenate([jnp.concatenate([inertia - m * C @ C, m * C], 2),
                            jnp.concatenate([-m * C, m * eye], 2)], 1)


def _symmetric(upper, ancestry):
    """The symmetric (n, n) matrix equal to upper at (i, k) with i ⪯ k (ancestry, diagonal
    included) and zero between joints on different branches."""
    U = jnp.where(ancestry, upper, 0.0)
    return U + U.T - jnp.diag(jnp.diagonal(U))


def _tree(model, frames, bodies):
    """Static index sets (numpy): ancestry (n, n) among the optimised joints (i ⪯ k), and which
    optimised joint moves each massive body (n, nm) and each frame (n, nf), as 0/1 floats."""
    topology = model.topology
    optimised = np.asarray(topology.optimised_joints, int)
    support = np.asarray(topology.joint_support, bool)[optimised]
    return dict(optimised=optimised, ancestry=support[:, optimised + 1],
                bodies=support[:, bodies].astype(float),
                frames=support[:, np.asarray(topology.frame_body, int)[list(frames)]].astype(float),
                prismatic=np.asarray(topology.joint_is_prismatic, bool)[optimised])


def _base_frame(model, s, frames):
    """The kinematics with the base at the origin, identity orientation, and what their derivatives
    in s (n,) need: a dict of the tree (``_tree``), the kinematics X (``bundle_from_poses``), the
    motion subspaces S (n, 6), the bodies' spatial inertias (nm, 6, 6), CoMs (nm, 3) [m] and masses
    (nm,) [kg], the subtrees' (composite) inertias (n, 6, 6), the CMM's columns as momenta about
    the origin F (6 + n, 6), the motions (6, 6) that ṗ and ω stand for (the CMM's first six
    columns), and the CoM's Jacobian Dx (n, 3) (rows: joints)."""
    q = jnp.concatenate([jnp.asarray(_IDENTITY_BASE, s.dtype), s])
    R_body, p_body = body_poses(model, q)
    composites = body_inertials_world(model, R_body, p_body)
    bodies, mass, com, inertia = composites
    tree = _tree(model, frames, bodies)
    axes, origins = joint_axes_world(model, R_body, p_body)
    axes, origins = axes[tree["optimised"]], origins[tree["optimised"]]
    prismatic = tree["prismatic"][:, None]
    S = jnp.concatenate([jnp.where(prismatic, 0.0, axes), jnp.where(prismatic, axes, jnp.cross(origins, axes))], 1)
    inertias = _spatial_inertia(mass, com, inertia)
    composite = jnp.einsum("kb,bxy->kxy", tree["bodies"], inertias)
    # The CMM's columns (eq. 4): ṗ and ω move the whole robot, ṡ_k the subtree of joint k.
    eye = jnp.eye(3, dtype=s.dtype)
    base = jnp.concatenate([jnp.concatenate([jnp.zeros_like(eye), eye], 1), jnp.concatenate([eye, jnp.zeros_like(eye)], 1)])
    F = jnp.concatenate([base @ jnp.sum(inertias, 0), jnp.einsum("kxy,ky->kx", composite, S)])
    X = bundle_from_poses(model, q, R_body, p_body, frames, composites)
    return dict(tree=tree, X=X, S=S, inertias=inertias, com=com, mass=mass, composite=composite, F=F,
                Dx=F[6:, 3:] / jnp.sum(mass), base=base)


def _cmm_jacobian(b):
    """∂J_CMM/∂s (6, 6 + n, n) in the base frame. Column c of the CMM is the momentum F_c of the
    bodies it moves, shifted to the CoM x (n_G = n − x × f). ∂F_c/∂s_i = S_i ×* F_c when joint i
    moves everything column c moves (i ⪯ c); when c ≺ i, only the subtree of i moves:
    S_i ×* (I_i S_c) − I_i (S_i × S_c), I_i its composite inertia; else zero."""
    S, composite, F, x = b["S"], b["composite"], b["F"], b["X"]["com"]
    ancestry = b["tree"]["ancestry"]
    n = S.shape[0]
    columns = jnp.concatenate([b["base"], S])  # (6 + n, 6): the motion each column stands for
    above = _cross_force(S[None], F[:, None])
    moved = jnp.einsum("ixy,cy->cix", composite, columns)
    below = _cross_force(S[None], moved) - jnp.einsum("ixy,ciy->cix", composite, _cross_motion(S[None], columns[:, None]))
    is_above = np.concatenate([np.zeros((6, n), bool), ancestry.T])
    is_below = np.concatenate([np.ones((6, n), bool), ancestry & ~np.eye(n, dtype=bool)])
    dF = jnp.where(is_above[..., None], above, 0.0) + jnp.where(is_below[..., None], below, 0.0)
    df = dF[..., 3:]
    dn = dF[..., :3] - jnp.cross(b["Dx"][None], F[:, None, 3:]) - jnp.cross(x, df)
    return jnp.transpose(jnp.concatenate([df, dn], -1), (2, 0, 1))


def _base_frame_jacobian(b):
    """∂X/∂s: each output of X with a trailing (n,) axis, in the base frame."""
    S, X = b["S"], b["X"]
    moves = b["tree"]["frames"].T[:, None, :]  # (nf, 1, n)
    points = X["frame_positions"]
    velocity = jnp.moveaxis(S[:, None, 3:] + jnp.cross(S[:, None, :3], points[None]), 0, -1)  # v_k + ω_k × p
    spin = jnp.einsum("kab,fbc->fack", jax.vmap(so3.skew)(S[:, :3]), X["frame_rotations"])  # [ω_k]× R_f
    return dict(com=b["Dx"].T, cmm=_cmm_jacobian(b), frame_positions=velocity * moves,
                frame_rotations=spin * moves[:, None])


def _points_curvature(S, ancestry, points, weights, moves):
    """Σ_p w_p · ∇²_s p for points p (m, 3) carried by the bodies (moves (n, m): which joint moves
    which), weights (m, 3): ∂²p/∂s_i∂s_k = ω_i × ∂p/∂s_k for i ⪯ k, so the entry is ω_i · u_k with
    u_k = v_k × W_k + M_k ω_k − tr(M_k) ω_k, W_k = Σ w_p and M_k = Σ p w_pᵀ over the subtree of k."""
    w, v = S[:, :3], S[:, 3:]
    W = moves @ weights
    M = jnp.einsum("km,ma,mb->kab", moves, points, weights)
    u = jnp.cross(v, W) + jnp.einsum("kab,kb->ka", M, w) - jnp.trace(M, axis1=1, axis2=2)[:, None] * w
    return _symmetric(w @ u.T, ancestry)


def _rotations_curvature(S, ancestry, rotations, weights, moves):
    """Σ_f ⟨W_f, ∇²_s R_f⟩ for frame rotations R_f (nf, 3, 3), weights W_f (nf, 3, 3):
    ∂²R/∂s_i∂s_k = [ω_i]× [ω_k]× R for i ⪯ k, and tr(Wᵀ [a]×[b]× R) = aᵀ N b − (a·b) tr N with
    N = R Wᵀ summed over the subtree of k."""
    w = S[:, :3]
    N = jnp.einsum("kf,fab,fcb->kac", moves, rotations, weights)
    u = jnp.einsum("kab,kb->ka", N, w) - jnp.trace(N, axis1=1, axis2=2)[:, None] * w
    return _symmetric(w @ u.T, ancestry)


def _momentum_curvature(b, y, nu):
    """∇²_s (y · J_CMM(s) ν) for one row weight y (6,) [linear; angular] and velocity ν (6 + n,),
    without its term through the CoM's own curvature, returned as the weight on x instead:
    (n, n), (3,).

    y · h_G = Ŷ · h_O with Ŷ = (y_a, y_l + x × y_a) and h_O = Σ_b I_b V_b the momentum about the
    origin. With Ŷ frozen, ∂h_O/∂s_k = P_k = S_k ×* H_k − I_k (S_k × V_k) (H_k the momentum of
    the subtree of k, V_k the velocity of joint k's body), and the entry (i ⪯ k) is
    α_i · P_k + β_i · Q_k with α_i = −S_i × Ŷ, β_i = S_i × V_i, Q_k = −I_k α_k − S_k ×* (I_k Ŷ).
    Ŷ moves with x: the cross terms (∂x/∂s_i × y_a) · ∂f/∂s_k, and (y_a × f) on ∇²x."""
    S, composite, ancestry, moves = b["S"], b["composite"], b["tree"]["ancestry"], b["tree"]["bodies"]
    y_l, y_a = y[:3], y[3:]
    Y = jnp.concatenate([y_a, y_l + jnp.cross(b["X"]["com"], y_a)])
    base = jnp.concatenate([nu[3:6], nu[:3]])
    joint = nu[6:, None] * S
    V_body = base + moves.T @ joint
    V_joint = base + jnp.where(ancestry, 1.0, 0.0).T @ joint
    momenta = jnp.einsum("bxy,by->bx", b["inertias"], V_body)
    H = moves @ momenta
    alpha = -_cross_motion(S, Y)
    beta = _cross_motion(S, V_joint)
    P = _cross_force(S, H) - jnp.einsum("kxy,ky->kx", composite, beta)
    Q = -jnp.einsum("kxy,ky->kx", composite, alpha) - _cross_force(S, jnp.einsum("kxy,y->kx", composite, Y))
    C = jnp.cross(b["Dx"], y_a) @ P[:, 3:].T
    return _symmetric(alpha @ P.T + beta @ Q.T, ancestry) + C + C.T, jnp.cross(y_a, jnp.sum(momenta, 0)[3:])


def _base_frame_curvature(b, weights):
    """Σ_a w_a ∇²_s X_a (n, n) for weights on the base frame's kinematics X (X's shapes). The CMM's
    weight (6, 6 + n) is taken row by row: Σ_r e_r · J_CMM W[r]ᵀ."""
    S, X, tree = b["S"], b["X"], b["tree"]
    rows, on_com = jax.vmap(lambda y, nu: _momentum_curvature(b, y, nu))(
        jnp.eye(6, dtype=S.dtype), weights["cmm"])
    com_weight = weights["com"] + jnp.sum(on_com, 0)
    share = (b["mass"] / jnp.sum(b["mass"]))[:, None]
    return (jnp.sum(rows, 0)
            + _points_curvature(S, tree["ancestry"], b["com"], share * com_weight, tree["bodies"])
            + _points_curvature(S, tree["ancestry"], X["frame_positions"], weights["frame_positions"], tree["frames"])
            + _rotations_curvature(S, tree["ancestry"], X["frame_rotations"], weights["frame_rotations"],
                                   tree["frames"]))


def _to_world(R, p, X):
    """The base frame's kinematics X seen with the base at position p (3,), orientation R (3, 3): the
    CMM maps ν with ṗ, ω in the world to the momentum in the world (rows and base columns turned)."""
    A = X["cmm"]
    rows = jnp.concatenate([R @ A[:3], R @ A[3:]])
    cmm = jnp.concatenate([rows[:, :3] @ R.T, rows[:, 3:6] @ R.T, rows[:, 6:]], 1)
    return dict(com=p + R @ X["com"], cmm=cmm, frame_positions=p + X["frame_positions"] @ R.T,
                frame_rotations=R @ X["frame_rotations"])


def _position_columns(X):
    """∂X/∂p (each output with a trailing (3,) axis): positions move one to one, nothing else does."""
    eye = jnp.eye(3, dtype=X["com"].dtype)
    return dict(com=eye, cmm=jnp.zeros(X["cmm"].shape + (3,), eye.dtype),
                frame_positions=jnp.broadcast_to(eye, X["frame_positions"].shape + (3,)),
                frame_rotations=jnp.zeros(X["frame_rotations"].shape + (3,), eye.dtype))


def _jacobian(q, b, base_jacobian):
    """∂κ/∂q, each output of ``centroidal_kinematics`` with a trailing (7 + n) axis, from the base
    frame's kinematics b (``_base_frame``) and their Jacobian (``_base_frame_jacobian``)."""
    X = b["X"]

    def world(rho):
        return _to_world(so3.quaternion_to_rotation(rho), q[:3], X)

    R = so3.quaternion_to_rotation(q[3:7])
    along_s = jax.vmap(lambda column: _to_world(R, jnp.zeros(3, q.dtype), column), in_axes=-1, out_axes=-1)(
        base_jacobian)
    return jax.tree.map(lambda *c: jnp.concatenate(c, -1), _position_columns(X), jax.jacfwd(world)(q[3:7]), along_s)


def _curvature(q, weights, b, base_jacobian):
    """Σ_a w_a ∇²_q κ_a (7 + n, 7 + n). κ = X turned by R(ρ) and moved by p, so the blocks are:
    along s, X's curvature weighted by the weights turned back (∂(w·κ)/∂X); across ρ and s,
    ∂²(w·κ)/∂ρ∂X contracted with ∂X/∂s; along ρ, the Hessian of w·κ in ρ alone (4 × 4). Every
    output is affine in p: its rows and columns are zero."""
    rho, X = q[3:7], b["X"]

    def weighted(rho, X):
        out = _to_world(so3.quaternion_to_rotation(rho), q[:3], X)
        return sum(jnp.sum(w * v) for w, v in zip(jax.tree.leaves(weights), jax.tree.leaves(out)))

    # ∂(w·κ)/∂X and its derivative along ρ's 4 tangents, from one linearisation
    pulled, along = jax.linearize(lambda rho: jax.grad(weighted, argnums=1)(rho, X), rho)
    across = jax.vmap(along, out_axes=-1)(jnp.eye(4, dtype=q.dtype))  # each output of X with a trailing (4,) axis
    rho_s = sum(jnp.tensordot(a, J, axes=(list(range(J.ndim - 1)), list(range(J.ndim - 1))))
                for a, J in zip(jax.tree.leaves(across), jax.tree.leaves(base_jacobian)))
    n = q.shape[0]
    return (jnp.zeros((n, n), q.dtype).at[3:7, 3:7].set(jax.hessian(weighted)(rho, X))
            .at[3:7, 7:].set(rho_s).at[7:, 3:7].set(rho_s.T)
            .at[7:, 7:].set(_base_frame_curvature(b, pulled)))


def centroidal_kinematics_derivatives(model, q, frames, weights):
    """``centroidal_kinematics`` at q, its Jacobian and Σ_a w_a ∇²_q κ_a for weights (a pytree of
    the kinematics' shapes): (κ, ∂κ/∂q (each output with a trailing (7 + n) axis), (7 + n, 7 + n)),
    from one pass of the tree recursions (``_base_frame``, ``_base_frame_jacobian``) shared by the
    Jacobian and the curvature."""
    q = check_configuration(model, q)
    b = _base_frame(model, q[7:], model.frame_indices(frames))
    base_jacobian = _base_frame_jacobian(b)
    value = _to_world(so3.quaternion_to_rotation(q[3:7]), q[:3], b["X"])
    return value, _jacobian(q, b, base_jacobian), _curvature(q, weights, b, base_jacobian)


def centroidal_kinematics_curvature(model, q, frames, weights):
    """Σ_a w_a ∇²_q κ_a(q) (7 + n, 7 + n) of ``centroidal_kinematics``' outputs κ for weights (a
    pytree of their shapes): the chain-rule term a transcription needs for its exact Lagrangian
    Hessian (``centroidal_kinematics_derivatives``, without the Jacobian)."""
    q = check_configuration(model, q)
    b = _base_frame(model, q[7:], model.frame_indices(frames))
    return _curvature(q, weights, b, _base_frame_jacobian(b))


def _bundle(model, q, frames):
    R_body, p_body = body_poses(model, q)
    return bundle_from_poses(model, q, R_body, p_body, frames)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _fast_bundle(model, q, frames):
    return _bundle(model, q, frames)


def _fast_bundle_jvp(frames, primals, tangents):
    model, q = primals
    model_dot, q_dot = tangents
    out = _bundle(model, q, frames)
    tangent = jax.tree.map(jnp.zeros_like, out)
    if not isinstance(q_dot, SymbolicZero):
        # One Jacobian (the tree recursions), then a product: cheap for many input tangents.
        b = _base_frame(model, q[7:], frames)
        tangent = jax.tree.map(lambda t, J: t + J @ q_dot, tangent, _jacobian(q, b, _base_frame_jacobian(b)))
    model_leaves = jax.tree.leaves(model_dot, is_leaf=lambda x: isinstance(x, SymbolicZero))
    if any(not isinstance(leaf, SymbolicZero) for leaf in model_leaves):
        model_dot = jax.tree.map(
            lambda t, m: jnp.zeros_like(m) if isinstance(t, SymbolicZero) else t,
            model_dot, model, is_leaf=lambda x: isinstance(x, SymbolicZero),
        )
        _, model_tangent = jax.jvp(lambda m: _bundle(m, q, frames), (model,), (model_dot,))
        tangent = jax.tree.map(jnp.add, tangent, model_tangent)
    return out, tangent


_fast_bundle.defjvp(_fast_bundle_jvp, symbolic_zeros=True)


def centroidal_kinematics(model, q, frames):
    """Everything the centroidal transcription needs at q, from one kinematics pass.

    frames: names or indices (static). Returns {com (3,), cmm (6, 6 + n), frame_positions
    (k, 3), frame_rotations (k, 3, 3)}, as ``com_position``, ``centroidal_momentum_matrix``
    and ``frame_poses`` would. Its forward-mode derivative computes the (7 + n)-column
    Jacobian once (the tree recursions) and applies it to every tangent, so ``jax.jacfwd`` over
    many variables that include q costs about as much as over q alone.
    """
    q = check_configuration(model, q)
    return _fast_bundle(model, q, model.frame_indices(frames))
