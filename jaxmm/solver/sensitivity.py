"""Derivatives of a stage-wise NLP's optimum with respect to its parameters, by implicit
differentiation of the interior-point KKT conditions at a converged ``interior_point.Solution``
(never by differentiating through the solver's iterations).

The solver stops on a point of the central path at a small barrier parameter μ (1e-11 by
default): with bound multipliers z (variables) and v (inequality slacks) it solves

    ∇_x f + Σ λ ∇c − z_L + z_U = 0,   c_E(x) = 0,   (x − l) z_L = μ,   (u − x) z_U = μ,
    λ_I = v_U − v_L,   (g(x) − l_g) v_L = μ,   (u_g − g(x)) v_U = μ.

Eliminating z and v leaves R(x, λ; p) = 0 with the Jacobian (the solver's own KKT matrix)

    K = [ H + Σ_x   J_Eᵀ   J_Iᵀ   ]    H = ∇²_xx L, Σ_x = z_L/(x − l) + z_U/(u − x),
        [ J_E       0      0      ]    Σ_g = v_L/(g − l_g) + v_U/(u_g − g) per inequality row,
        [ J_I       0     −Σ_g⁻¹  ]

and the implicit function theorem gives d(x*, λ*)/dp = −K⁻¹ ∂R/∂p, with p the NLP pytree itself:
its ``args``, ``knot_data`` and every bound (a bound enters through Σ: an active bound, Σ ≈ λ²/μ,
drags its variable along; an inactive one, Σ ≈ μ/d², does not). This is the derivative with the
active set fixed, smoothed by μ: where the solution is strictly complementary it equals the
active-set derivative up to O(μ); where it is not — the relaxed complementarity of contact
problems, f_z = c_z = 0 with both bounds active, whose active rows are linearly dependent
(LICQ fails) — the active-set KKT matrix is singular and the barrier's is not, and it gives the
derivative of the solution path at μ. Fixed variables (l = u) and inequality rows without a
finite bound are solved by substitution (x = l; λ = 0).

K is never factored densely: ``vjp`` solves K w = (x̄, λ̄) (the adjoint), ``jvp`` solves
K v = −∂R/∂p ṗ (``jax.linearize``), both by GMRES on the Jacobi-scaled K (the barrier terms
span 1e-20 … 1e20), preconditioned by the block Cholesky (``linalg``) of the condensed,
regularised matrix α (H + Σ_x) + δ I + J̃ᵀ (D̃ + I/ρ)⁻¹ J̃ (the Hessian divided by its largest
entry, α; every row by its largest entry, J̃ = S J; D̃ = S² Σ_g⁻¹ / α), run until K's scaled
relative residual is below ``Options.tolerance``: the regularisation costs iterations, not
accuracy. ``Diagnostics`` reports the residual, recomputed independently with
``jax.vjp``/``jax.jvp`` of R, the shift the factorisation needed and the ``ActiveSet.margin``
(how clearly the solution separates active from inactive bounds).
"""

import dataclasses

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from jaxmm.solver import interior_point as ip
from jaxmm.solver import linalg, newton, rows
from jaxmm import stagewise

GROUPS = ip.GROUPS
_TINY = 1e-300


@dataclasses.dataclass(frozen=True)
class Options:
    """Settings of the sensitivity computation (static).

    threshold: a bound with distance d and multiplier λ ≥ 0 on its side is active when
    λ > threshold · d (``active_set``, reported as ``Diagnostics.margin``); penalty: ρ of the
    condensed preconditioner α (H + Σ_x) + δ I + J̃ᵀ (D̃ + I/ρ)⁻¹ J̃ (see the module docstring);
    min_regularisation, max_regularisation: the first shift δ of the factorisation (×10 until it
    succeeds) and the largest; tolerance: relative residual of the unregularised KKT
    system at which the solve stops; krylov_dimension: GMRES steps per cycle; max_cycles: GMRES
    cycles at most;
    max_residual, strict: with ``strict``, ``differentiable_solve`` returns NaN gradients unless
    ``Diagnostics.reliable(max_residual)``.
    """

    threshold: float = 1.0
    penalty: float = 1e8
    min_regularisation: float = 1e-8
    max_regularisation: float = 1e-2
    tolerance: float = 1e-13
    krylov_dimension: int = 20
    max_cycles: int = 10
    max_residual: float = 1e-8
    strict: bool = True


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ActiveSet:
    """Which bounds hold with equality at a solution (booleans) and how clearly.

    z_lower, z_upper: (K, nz); theta_lower, theta_upper: (ng,); path_lower, path_upper:
    (K, mg); transition_lower, transition_upper: (K − 1, mh). A fixed variable (lower = upper)
    and an inequality row with equal bounds count as active at their lower bound.
    margin: () the smallest |log₁₀(λ / (threshold · d))| over every finite bound that is not
    fixed: how far the solution is from the activity threshold, in decades (∞ if no such
    bound). An interior-point solution at barrier parameter μ has λ d ≈ μ on every bound, so a
    strictly complementary one has a margin near |log₁₀ μ| (≈ 11 at μ = 1e-11); a margin below
    ≈ 2 means some bound is weakly active or degenerate and the derivative is one-sided at best.
    """

    z_lower: jax.Array
    z_upper: jax.Array
    theta_lower: jax.Array
    theta_upper: jax.Array
    path_lower: jax.Array
    path_upper: jax.Array
    transition_lower: jax.Array
    transition_upper: jax.Array
    margin: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Diagnostics:
    """How far a sensitivity can be trusted.

    residual: () ‖K w − rhs‖∞ / ‖rhs‖∞ for the unregularised KKT system, in the normalised,
    Jacobi-scaled units of the module docstring, recomputed at the end with automatic
    differentiation of R, independently of the block assembly: a residual that stays large
    means the right-hand side has a component K cannot produce (a singular K: dependent
    equality rows or flat curvature, felt by this cotangent) and the result is not a derivative;
    cycles: () GMRES cycles taken; regularisation: () the shift δ the factorisation needed
    (``Options.min_regularisation`` when the condensed matrix is positive definite; larger
    values signal negative curvature on the null space of the equality rows: second-order
    sufficiency fails); factored: () a factorisation was found with
    δ ≤ ``Options.max_regularisation``; margin: the ``ActiveSet.margin``; converged: () the
    solve's status was ``CONVERGED``.
    """

    residual: jax.Array
    cycles: jax.Array
    regularisation: jax.Array
    factored: jax.Array
    margin: jax.Array
    converged: jax.Array

    def reliable(self, max_residual=1e-8):
        """() True when the solve converged, K was factored and its residual is ≤ max_residual."""
        return self.converged & self.factored & (self.residual <= max_residual)


def _side(multiplier, distance, possible, threshold):
    """Activity of one side of a set of bounds, and its margin in decades."""
    active = possible & (multiplier > threshold * distance)
    decades = jnp.abs(
        jnp.log10(jnp.maximum(multiplier, _TINY)) - jnp.log10(jnp.maximum(threshold * distance, _TINY))
    )
    return active, jnp.min(jnp.where(possible, decades, jnp.inf), initial=jnp.inf)


def active_set(nlp, solution, options=Options()):
    """The active set of a ``Solution`` of ``nlp``: an ``ActiveSet``.

    A bound with distance d ≥ 0 from the solution and multiplier λ ≥ 0 on its side is active
    when λ > threshold · d. Variable bounds use the solver's bound multipliers
    (``Solution.bound_multipliers``, the solver's cost scaling) and distances in the NLP's
    variables; inequality rows use the NLP-unit multipliers (``Solution.multipliers``: λ > 0 is
    the upper side, λ < 0 the lower) and distances in the rows' units. At an interior-point
    solution λ d ≈ μ ≪ 1 on every bound, so λ ≫ d or λ ≪ d and the unit factors between these
    scalings (bounded by the solver's cost and row scales) do not move the decision.
    """
    (zl, tl, _, _), (zu, tu, _, _) = solution.bound_multipliers
    r = stagewise.residuals(nlp, solution.Z, solution.theta)
    y = solution.multipliers
    margins = []

    def variable(value, lower, upper, lower_multiplier, upper_multiplier):
        fixed = (lower == upper) & jnp.isfinite(lower)
        at_lower, m_lower = _side(lower_multiplier, value - lower, jnp.isfinite(lower) & ~fixed, options.threshold)
        at_upper, m_upper = _side(upper_multiplier, upper - value, jnp.isfinite(upper) & ~fixed, options.threshold)
        margins.extend([m_lower, m_upper])
        return at_lower | fixed, at_upper & ~at_lower

    def row(value, multiplier, lower, upper):
        fixed = jnp.broadcast_to((lower == upper) & jnp.isfinite(lower), value.shape)
        at_lower, m_lower = _side(-multiplier, value - lower, jnp.isfinite(lower) & ~fixed, options.threshold)
        at_upper, m_upper = _side(multiplier, upper - value, jnp.isfinite(upper) & ~fixed, options.threshold)
        margins.extend([m_lower, m_upper])
        return at_lower | fixed, at_upper & ~at_lower

    z_lower, z_upper = variable(solution.Z, nlp.z_lower, nlp.z_upper, zl, zu)
    theta_lower, theta_upper = variable(solution.theta, nlp.theta_lower, nlp.theta_upper, tl, tu)
    path_lower, path_upper = row(r.path_inequality, y.path_inequality, nlp.path_lower, nlp.path_upper)
    transition_lower, transition_upper = row(
        r.transition_inequality, y.transition_inequality, nlp.transition_lower, nlp.transition_upper
    )
    return ActiveSet(
        z_lower=z_lower, z_upper=z_upper, theta_lower=theta_lower, theta_upper=theta_upper,
        path_lower=path_lower, path_upper=path_upper, transition_lower=transition_lower,
        transition_upper=transition_upper, margin=jnp.min(jnp.stack(margins)),
    )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _Barrier:
    """The barrier terms at a solution, in the NLP's units (constants of the linearisation).

    Per primal leaf (Z (K, nz), θ (ng,)): lower, upper: Σ_L = z_L / (x − l), Σ_U = z_U / (u − x)
    (0 without a finite bound); fixed: l = u. Per inequality group (path (K, mg), transition
    (K − 1, mh)): row_lower, row_upper: σ_L, σ_U, the same for the row's slack; row_fixed:
    l = u (the row is an equality); row_free: no finite bound (its multiplier is 0)."""

    lower: tuple
    upper: tuple
    fixed: tuple
    row_lower: tuple
    row_upper: tuple
    row_fixed: tuple
    row_free: tuple


def _barrier_terms(nlp, solution):
    """``_Barrier`` from the solver's bound multipliers, slacks and scaling."""
    cost_scale, row_scale = solution.scaling
    zl, zu = solution.bound_multipliers

    def variable(value, lower, upper, ml, mu):
        fixed = (lower == upper) & jnp.isfinite(lower)
        has_l, has_u = jnp.isfinite(lower) & ~fixed, jnp.isfinite(upper) & ~fixed
        sl = jnp.where(has_l, ml / cost_scale / jnp.where(has_l, value - lower, 1.0), 0.0)
        su = jnp.where(has_u, mu / cost_scale / jnp.where(has_u, upper - value, 1.0), 0.0)
        return sl, su, fixed

    def row(slack, lower, upper, ml, mu, scale):
        lower, upper = jnp.broadcast_to(lower, slack.shape), jnp.broadcast_to(upper, slack.shape)
        fixed = (lower == upper) & jnp.isfinite(lower)
        has_l, has_u = jnp.isfinite(lower) & ~fixed, jnp.isfinite(upper) & ~fixed
        # A slack s = scale · g carries z / d; per unit of g and of the NLP's cost: scale² / cost_scale.
        factor = scale ** 2 / cost_scale
        sl = jnp.where(has_l, factor * ml / jnp.where(has_l, slack - scale * lower, 1.0), 0.0)
        su = jnp.where(has_u, factor * mu / jnp.where(has_u, scale * upper - slack, 1.0), 0.0)
        return sl, su, fixed, ~(has_l | has_u | fixed)

    Z = variable(solution.Z, nlp.z_lower, nlp.z_upper, zl[0], zu[0])
    T = variable(solution.theta, nlp.theta_lower, nlp.theta_upper, zl[1], zu[1])
    P = row(solution.slacks[0], nlp.path_lower, nlp.path_upper, zl[2], zu[2], row_scale[2])
    Q = row(solution.slacks[1], nlp.transition_lower, nlp.transition_upper, zl[3], zu[3], row_scale[3])
    return jax.lax.stop_gradient(_Barrier(
        lower=(Z[0], T[0]), upper=(Z[1], T[1]), fixed=(Z[2], T[2]),
        row_lower=(P[0], Q[0]), row_upper=(P[1], Q[1]), row_fixed=(P[2], Q[2]), row_free=(P[3], Q[3]),
    ))


def _row_masks(barrier, y):
    """Per group, True on the rows of the KKT system (every equality row; inequality rows with
    a finite bound)."""
    return (
        jnp.ones(y.path_equality.shape, bool),
        jnp.ones(y.transition_equality.shape, bool),
        ~barrier.row_free[0],
        ~barrier.row_free[1],
    )


def _finite(bound, mask):
    return jnp.where(mask, bound, 0.0)


def _kkt_residual(nlp, barrier, Z, theta, y):
    """R(x, λ; p) of the module docstring, up to constants: (R_Z (K, nz), R_θ (ng,), R_λ a
    ``Multipliers``). Only its derivatives at the solution are used."""

    def lagrangian(Z, theta):
        r = stagewise.residuals(nlp, Z, theta)
        return r.cost + sum(jnp.vdot(getattr(y, g), getattr(r, g)) for g in GROUPS), r

    (gz, gt), r = jax.grad(lagrangian, argnums=(0, 1), has_aux=True)(Z, theta)

    def variable(value, gradient, lower, upper, sl, su, fixed):
        stationary = (gradient + (sl + su) * value - sl * _finite(lower, sl > 0) - su * _finite(upper, su > 0))
        return jnp.where(fixed, value - _finite(lower, fixed), stationary)

    def inequality(value, multiplier, lower, upper, sl, su, fixed, free):
        lower, upper = jnp.broadcast_to(lower, value.shape), jnp.broadcast_to(upper, value.shape)
        sigma = sl + su
        inverse = 1.0 / jnp.where(sigma > 0, sigma, 1.0)
        slack = (multiplier + sl * _finite(lower, sl > 0) + su * _finite(upper, su > 0)) * inverse
        return jnp.where(free, multiplier, jnp.where(fixed, value - _finite(lower, fixed), value - slack))

    return (
        variable(Z, gz, nlp.z_lower, nlp.z_upper, barrier.lower[0], barrier.upper[0], barrier.fixed[0]),
        variable(theta, gt, nlp.theta_lower, nlp.theta_upper, barrier.lower[1], barrier.upper[1], barrier.fixed[1]),
        ip.Multipliers(
            path_equality=r.path_equality,
            transition_equality=r.transition_equality,
            path_inequality=inequality(r.path_inequality, y.path_inequality, nlp.path_lower, nlp.path_upper,
                                       barrier.row_lower[0], barrier.row_upper[0], barrier.row_fixed[0],
                                       barrier.row_free[0]),
            transition_inequality=inequality(r.transition_inequality, y.transition_inequality, nlp.transition_lower,
                                             nlp.transition_upper, barrier.row_lower[1], barrier.row_upper[1],
                                             barrier.row_fixed[1], barrier.row_free[1]),
        ),
    )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _KKT:
    """The normalised KKT system on (x_F, λ_𝒜): Hessian blocks α (H + Σ) on F (D, L, B, C),
    scaled rows J̃ = S J_𝒜F per group and their barrier diagonal D̃ = S² Σ_s⁻¹ / α (0 on
    equalities), the block Cholesky of α (H + Σ) + δ I + J̃ᵀ (D̃ + I/ρ)⁻¹ J̃ (identity on the fixed
    variables), masks and scales. Unknowns (w_F, w̃) relate to (w_F, w_𝒜) by w_𝒜 = S w̃ / α."""

    hessian: tuple
    jacobians: tuple
    row_diagonal: tuple  # D̃ per group
    chol: linalg.BlockCholesky
    regularisation: jax.Array  # δ of the factor
    free_z: jax.Array  # (K, nz) 1 on F
    free_theta: jax.Array  # (ng,)
    row_scale: tuple  # S per group, 0 on the rows outside 𝒜
    hessian_scale: jax.Array  # α
    jacobi: tuple  # (K, nz), (ng,), per group: 1/√max(1, |diagonal|) of the normalised K
    penalty: float = dataclasses.field(metadata=dict(static=True))


def _kkt(nlp, Z, theta, y, barrier, options):
    """Assemble and factor the normalised, condensed KKT matrix (a ``_KKT``)."""
    K = Z.shape[0]
    B = stagewise.blocks(nlp, Z, theta)
    free_z = (~barrier.fixed[0]).astype(Z.dtype)
    free_t = (~barrier.fixed[1]).astype(Z.dtype)
    jacobians, scales = [], []
    supports = stagewise.row_supports(nlp)
    for group, mask in zip(GROUPS, _row_masks(barrier, y)):
        r = rows.group_rows(B, group, supports.get(group))
        if r.jn is None:
            r = dataclasses.replace(r, jz=r.jz * free_z[:, None, :], jt=r.jt * free_t)
        else:
            r = dataclasses.replace(r, jz=r.jz * free_z[:-1, None, :], jt=r.jt * free_t, jn=r.jn * free_z[1:, None, :])
        largest = jnp.max(jnp.abs(r.jz), axis=-1, initial=0.0)
        largest = jnp.maximum(largest, jnp.max(jnp.abs(r.jt), axis=-1, initial=0.0))
        if r.jn is not None:
            largest = jnp.maximum(largest, jnp.max(jnp.abs(r.jn), axis=-1, initial=0.0))
        # A row with no entry on F is either redundant or an infeasible perturbation; scale 1
        # keeps it zero and lets the residual report the latter.
        scale = jnp.where(mask, 1.0 / jnp.where(largest > 0, largest, 1.0), 0.0)
        scales.append(scale)
        jacobians.append(rows.scaled(r, scale))
    cost_zz = B.cost_zz.dense()
    D, L, Bd, C = rows.add(
        (cost_zz, jnp.zeros_like(cost_zz[1:]), B.cost_ztheta, B.cost_thetatheta),
        stagewise.constraint_curvature(nlp, Z, theta, *(getattr(y, g) for g in GROUPS),
                                       path_linearisation=B.path_linearisation),
    )
    masked = (
        free_z[:, :, None] * D * free_z[:, None, :],
        free_z[1:, :, None] * L * free_z[:-1, None, :],
        free_z[:, :, None] * Bd * free_t[None, None, :],
        free_t[:, None] * C * free_t[None, :],
    )
    largest = jnp.max(jnp.stack([jnp.max(jnp.abs(b), initial=0.0) for b in masked]))
    alpha = 1.0 / jnp.where(largest > 0, largest, 1.0)
    sigma_z = (barrier.lower[0] + barrier.upper[0]) * free_z
    sigma_t = (barrier.lower[1] + barrier.upper[1]) * free_t
    hessian = (alpha * (masked[0] + jax.vmap(jnp.diag)(sigma_z)), alpha * masked[1], alpha * masked[2],
               alpha * (masked[3] + jnp.diag(sigma_t)))
    row_diagonal = [jnp.zeros_like(scales[0]), jnp.zeros_like(scales[1])]
    for i in range(2):
        sigma = barrier.row_lower[i] + barrier.row_upper[i]
        inverse = jnp.where(sigma > 0, 1.0 / jnp.where(sigma > 0, sigma, 1.0), 0.0)
        row_diagonal.append(scales[2 + i] ** 2 * inverse / alpha)
    weights = [1.0 / (d + 1.0 / options.penalty) for d in row_diagonal]
    D, L, Bd, C = rows.grams(jacobians, weights, K, into=hessian)

    # The factor only preconditions GMRES, which solves the unregularised system: a shift δ I on
    # F costs iterations, not accuracy. Pivots of the condensed matrix below ≈ ρ ε (1e-8 at ρ = 1e8)
    # are rounding, so δ starts there: on iRonCub's take-off, whose reduced Hessian has flat
    # directions (eigenvalues −3e-12 relative), δ = 1e-10 left the preconditioner nearly
    # singular and GMRES at a residual of 8e-5 after 10 cycles; δ = 1e-8 reached 1e-10.
    delta, chol, _, _ = newton.factor(
        lambda delta: (D, L, Bd, C), lambda delta: (1 - free_z + delta * free_z, 1 - free_t + delta * free_t),
        jnp.asarray(options.min_regularisation, Z.dtype), lambda delta: 10 * delta, jnp.asarray(True),
        options.max_regularisation, K)
    # Active bounds put Σ ≈ λ²/μ (up to 1e20) on the diagonal; without a symmetric diagonal
    # scaling, a residual relative to such entries says nothing about the O(1) rows.
    def jacobi(diagonal):
        return 1.0 / jnp.sqrt(jnp.maximum(1.0, jnp.abs(diagonal)))

    scaling = (jacobi(jax.vmap(jnp.diag)(hessian[0])), jacobi(jnp.diag(hessian[3])),
               tuple(jacobi(d) for d in row_diagonal))
    return _KKT(hessian, tuple(jacobians), tuple(row_diagonal), chol, delta, free_z, free_t, tuple(scales), alpha,
                scaling, options.penalty)


def _apply(kkt, wz, wt, wc):
    """K (normalised) times (w_F, w̃)."""
    K = wz.shape[0]
    hz, ht = linalg.matvec(*kkt.hessian, wz, wt)
    for r, c in zip(kkt.jacobians, wc):
        pz, pt = rows.pull(r, c, K)
        hz, ht = hz + pz, ht + pt
    return hz, ht, tuple(rows.apply(r, wz, wt) - d * c for r, d, c in zip(kkt.jacobians, kkt.row_diagonal, wc))


def _solve_regularised(kkt, ez, et, ec):
    """Solve [α(H + Σ) + δ I, J̃ᵀ; J̃, −(D̃ + I/ρ)] d = e through the condensed matrix."""
    K = ez.shape[0]
    weights = [1.0 / (d + 1.0 / kkt.penalty) for d in kkt.row_diagonal]
    rz, rt = ez, et
    for r, w, c in zip(kkt.jacobians, weights, ec):
        pz, pt = rows.pull(r, w * c, K)
        rz, rt = rz + pz, rt + pt
    dz, dt = linalg.solve(kkt.chol, rz * kkt.free_z, rt * kkt.free_theta)
    dz, dt = dz * kkt.free_z, dt * kkt.free_theta
    return dz, dt, tuple(w * (rows.apply(r, dz, dt) - c) for r, w, c in zip(kkt.jacobians, weights, ec))


def _max_abs(tree):
    return jnp.max(jnp.stack([jnp.max(jnp.abs(leaf), initial=0.0) for leaf in jax.tree.leaves(tree)]))


def _gmres_cycle(apply, precondition, r, dimension):
    """One cycle of right-preconditioned GMRES on flat vectors: the correction d = M⁻¹ V y that
    minimises ‖r − K d‖₂ over the Krylov space of K M⁻¹ and r (``dimension`` Arnoldi steps,
    Gram–Schmidt applied twice). The small least-squares problem is solved by SVD, which keeps
    a singular (consistent) K — dependent active rows — from producing non-finite numbers."""
    beta = jnp.linalg.norm(r)
    V = jnp.zeros((dimension + 1, r.size), r.dtype).at[0].set(jnp.where(beta > 0, r / jnp.where(beta > 0, beta, 1.0), 0.0))
    H = jnp.zeros((dimension + 1, dimension), r.dtype)

    def arnoldi(j, carry):
        V, H = carry
        w = apply(precondition(V[j]))
        h = V @ w
        w = w - V.T @ h
        correction = V @ w
        w, h = w - V.T @ correction, h + correction
        norm = jnp.linalg.norm(w)
        # A breakdown (norm 0) means the space is invariant: later columns stay zero.
        V = V.at[j + 1].set(jnp.where(norm > 0, w / jnp.where(norm > 0, norm, 1.0), 0.0))
        return V, H.at[:, j].set(h.at[j + 1].set(norm))

    V, H = jax.lax.fori_loop(0, dimension, arnoldi, (V, H))
    y, _, _, _ = jnp.linalg.lstsq(H, jnp.zeros(dimension + 1, r.dtype).at[0].set(beta))
    return precondition(V[:-1].T @ y)


def _solve_kkt(kkt, rhs, options):
    """Solve the normalised, unregularised K w = rhs: cycles of GMRES (``krylov_dimension``
    steps each) on the residual, preconditioned by the regularised factor, until the true
    residual is ≤ tolerance relative to rhs. Returns (w, cycles).

    Plain iterative refinement with the same factor converges at the rate of its slowest mode
    (≈ 0.96 per step on iRonCub, whose reduced Hessian has near-flat directions); the Krylov
    space removes those few slow modes in a few steps."""
    flat, unravel = jax.flatten_util.ravel_pytree(rhs)
    jacobi = jax.flatten_util.ravel_pytree(kkt.jacobi)[0]  # GMRES runs on S K S, S = diag(jacobi)
    flat = jacobi * flat

    def apply(w):
        return jacobi * jax.flatten_util.ravel_pytree(_apply(kkt, *unravel(jacobi * w)))[0]

    def precondition(e):
        return jax.flatten_util.ravel_pytree(_solve_regularised(kkt, *unravel(e / jacobi)))[0] / jacobi

    size = jnp.maximum(jnp.max(jnp.abs(flat), initial=0.0), _TINY)

    def running(carry):
        _, e, k = carry
        return (k < options.max_cycles) & (jnp.max(jnp.abs(e), initial=0.0) > options.tolerance * size)

    def cycle(carry):
        w, e, k = carry
        w = w + _gmres_cycle(apply, precondition, e, options.krylov_dimension)
        return w, flat - apply(w), k + 1

    w, _, k = jax.lax.while_loop(running, cycle, (jnp.zeros_like(flat), flat, jnp.asarray(0)))
    return unravel(jacobi * w), k


def _normalise(kkt, gz, gt, gc):
    """Right-hand side (x rows, λ rows in NLP units) → the normalised system's, restricted to F, 𝒜."""
    return (kkt.hessian_scale * gz * kkt.free_z, kkt.hessian_scale * gt * kkt.free_theta,
            tuple(s * c for s, c in zip(kkt.row_scale, gc)))


def _core(kkt, gz, gt, gc, options):
    """Solve K (w_F, w_𝒜) = (g_F, g_𝒜) in NLP units (𝒜: the rows of the system): (w_z, w_θ, w_𝒜 per
    group, cycles)."""
    (wz, wt, wc), k = _solve_kkt(kkt, _normalise(kkt, gz, gt, gc), options)
    return wz, wt, tuple(s * c / kkt.hessian_scale for s, c in zip(kkt.row_scale, wc)), k


def _relative_residual(kkt, ez, et, ec, gz, gt, gc):
    """‖S normalised e‖∞ / ‖S normalised g‖∞ for a residual e of the system with right-hand side
    g (S: the Jacobi scaling GMRES works with)."""

    def scaled(z, t, c):
        nz, nt, nc = _normalise(kkt, z, t, c)
        sz, st, sc = kkt.jacobi
        return nz * sz, nt * st, tuple(a * b for a, b in zip(nc, sc))

    return _max_abs(scaled(ez, et, ec)) / jnp.maximum(_max_abs(scaled(gz, gt, gc)), _TINY)


def _split(tree):
    """(inexact leaves, rebuild(inexact leaves) → tree) for differentiating a pytree with integer leaves."""
    leaves, treedef = jax.tree.flatten(tree)
    inexact = [jnp.issubdtype(jnp.result_type(leaf), jnp.inexact) for leaf in leaves]

    def rebuild(values):
        values = iter(values)
        return jax.tree.unflatten(treedef, [next(values) if f else leaf for leaf, f in zip(leaves, inexact)])

    return [leaf for leaf, f in zip(leaves, inexact) if f], rebuild, (leaves, inexact, treedef)


def _cotangent(structure, values):
    """A cotangent of the tree from its inexact leaves' cotangents (float0 zeros elsewhere)."""
    leaves, inexact, treedef = structure
    values = iter(values)
    return jax.tree.unflatten(treedef, [
        next(values) if f else np.zeros(np.shape(leaf), jax.dtypes.float0) for leaf, f in zip(leaves, inexact)
    ])


def _as_tuple(multipliers):
    return tuple(getattr(multipliers, g) for g in GROUPS)


def _setup(nlp, solution, options):
    barrier = _barrier_terms(nlp, solution)
    y = solution.multipliers
    kkt = _kkt(nlp, solution.Z, solution.theta, y, barrier, options)
    return barrier, y, kkt


def _margin(nlp, solution, options):
    return active_set(nlp, solution, options).margin


def _pullback(nlp, solution, Z_bar, theta_bar, multipliers_bar, options):
    """``vjp`` on the inexact leaves: (their cotangents, the tree structure, ``Diagnostics``)."""
    barrier, y, kkt = _setup(nlp, solution, options)
    Z, theta = solution.Z, solution.theta
    if multipliers_bar is None:
        lam_bar = tuple(jnp.zeros_like(v) for v in _as_tuple(y))
    else:
        lam_bar = _as_tuple(multipliers_bar)
    wz, wt, wc, k = _core(kkt, Z_bar, theta_bar, lam_bar, options)
    params, rebuild, structure = _split(nlp)

    def residual(Z, theta, y, params):
        return _kkt_residual(rebuild(params), barrier, Z, theta, y)

    _, pull = jax.vjp(residual, Z, theta, y, params)
    # The rows of Mᵀw = ȳ on B and on the inactive rows are solved by substitution.
    pz, pt, py, _ = pull((wz, wt, ip.Multipliers(*wc)))
    wz = jnp.where(kkt.free_z > 0, wz, Z_bar - pz)
    wt = jnp.where(kkt.free_theta > 0, wt, theta_bar - pt)
    wc = tuple(jnp.where(s != 0, c, b - p) for s, c, b, p in zip(kkt.row_scale, wc, lam_bar, _as_tuple(py)))
    pz, pt, py, p_bar = pull((wz, wt, ip.Multipliers(*wc)))
    diagnostics = Diagnostics(
        residual=_relative_residual(kkt, pz - Z_bar, pt - theta_bar,
                                    tuple(p - b for p, b in zip(_as_tuple(py), lam_bar)), Z_bar, theta_bar, lam_bar),
        cycles=k, regularisation=kkt.regularisation, factored=kkt.chol.ok,
        margin=_margin(nlp, solution, options),
        converged=solution.status == int(ip.Status.CONVERGED),
    )
    return [-p for p in p_bar], structure, diagnostics


def vjp(nlp, solution, Z_bar, theta_bar, multipliers_bar=None, options=Options()):
    """Vector–Jacobian product of the optimum with respect to the NLP.

    nlp: the ``StagewiseNLP`` that was solved; solution: its converged ``Solution``;
    Z_bar (K, nz), theta_bar (ng,): cotangents of Z*, θ*; multipliers_bar: a ``Multipliers`` of
    cotangents of λ* (None: zeros; the entries of rows without a finite bound are cotangents
    of a constant 0).
    Returns (nlp_bar, diagnostics): nlp_bar has the structure of ``nlp`` with the cotangent of
    every inexact leaf (``args``, ``knot_data`` and the bounds) and float0 zeros on integer
    leaves; ``Diagnostics``.
    """
    values, structure, diagnostics = _pullback(nlp, solution, Z_bar, theta_bar, multipliers_bar, options)
    return _cotangent(structure, values), diagnostics


def jvp(nlp, solution, nlp_dot, options=Options()):
    """Jacobian–vector product of the optimum with respect to the NLP.

    nlp_dot: a tangent with the structure of ``nlp`` (its integer leaves are ignored).
    Returns (Z_dot (K, nz), theta_dot (ng,), multipliers_dot (a ``Multipliers``), diagnostics).
    """
    barrier, y, kkt = _setup(nlp, solution, options)
    Z, theta = solution.Z, solution.theta
    params, rebuild, (_, inexact, _) = _split(nlp)
    params_dot = [t for t, f in zip(jax.tree.leaves(nlp_dot), inexact) if f]

    def residual(Z, theta, y, params):
        return _kkt_residual(rebuild(params), barrier, Z, theta, y)

    _, linear = jax.linearize(residual, Z, theta, y, params)
    zeros_z, zeros_t, zeros_y = jnp.zeros_like(Z), jnp.zeros_like(theta), jax.tree.map(jnp.zeros_like, y)
    rz, rt, ry = jax.tree.map(jnp.negative, linear(zeros_z, zeros_t, zeros_y, params_dot))
    ry = _as_tuple(ry)
    # M v = r: on B and the inactive rows v is r itself; their coupling into F and 𝒜 moves to
    # the right-hand side of the KKT system.
    vz_b = jnp.where(kkt.free_z > 0, 0.0, rz)
    vt_b = jnp.where(kkt.free_theta > 0, 0.0, rt)
    vc_i = tuple(jnp.where(s != 0, 0.0, r) for s, r in zip(kkt.row_scale, ry))
    cz, ct, cy = linear(vz_b, vt_b, ip.Multipliers(*vc_i), [jnp.zeros_like(p) for p in params])
    vz, vt, vc, k = _core(kkt, rz - cz, rt - ct, tuple(r - c for r, c in zip(ry, _as_tuple(cy))), options)
    vz, vt = vz + vz_b, vt + vt_b
    vc = tuple(jnp.where(s != 0, v, i) for s, v, i in zip(kkt.row_scale, vc, vc_i))
    ez, et, ey = linear(vz, vt, ip.Multipliers(*vc), [jnp.zeros_like(p) for p in params])
    diagnostics = Diagnostics(
        residual=_relative_residual(kkt, ez - rz, et - rt, tuple(e - r for e, r in zip(_as_tuple(ey), ry)), rz, rt, ry),
        cycles=k, regularisation=kkt.regularisation, factored=kkt.chol.ok,
        margin=_margin(nlp, solution, options),
        converged=solution.status == int(ip.Status.CONVERGED),
    )
    return vz, vt, ip.Multipliers(*vc), diagnostics


def differentiable_solve(nlp, Z0, theta0, options=ip.Options(), multipliers=None, bound_multipliers=None,
                         sensitivity=Options()):
    """``interior_point.solve`` whose ``Solution`` is differentiable with respect to ``nlp`` (its
    ``args``, ``knot_data`` and bounds) in reverse mode (``jax.grad``, ``jax.vjp``).

    The derivatives of Z, θ, the multipliers and the objective are implicit (``vjp``); the
    starting point and warm-start multipliers get zero cotangents (the optimum does not depend
    on them locally); the statistics (status, violation, history, …) carry no gradient. With
    ``sensitivity.strict`` the gradient is NaN when the solve did not converge, the condensed
    KKT matrix was not positive definite or the adjoint residual exceeds
    ``sensitivity.max_residual``: call ``vjp`` on the solution for the ``Diagnostics``.
    Jittable and vmappable; ``options`` and ``sensitivity`` are static.
    """
    return _differentiable(options, sensitivity, nlp, Z0, theta0, multipliers, bound_multipliers)


def _primal(options, sensitivity, nlp, Z0, theta0, multipliers, bound_multipliers):
    return ip.solve(nlp, Z0, theta0, options, multipliers, bound_multipliers)


_differentiable = jax.custom_vjp(_primal, nondiff_argnums=(0, 1))


def _forward(options, sensitivity, nlp, Z0, theta0, multipliers, bound_multipliers):
    solution = ip.solve(nlp, Z0, theta0, options, multipliers, bound_multipliers)
    return solution, (nlp, solution, Z0, theta0, multipliers, bound_multipliers)


def _zero_cotangent(tree):
    return jax.tree.map(
        lambda leaf: jnp.zeros_like(leaf) if jnp.issubdtype(jnp.result_type(leaf), jnp.inexact)
        else np.zeros(np.shape(leaf), jax.dtypes.float0), tree)


def _backward(options, sensitivity, saved, solution_bar):
    nlp, solution, Z0, theta0, multipliers, bound_multipliers = saved
    # The objective f(x*(p); p): its cotangent adds ō ∇ₓf to x̄ and ō ∂f/∂p to p̄.
    params, rebuild, _ = _split(nlp)
    _, cost_pull = jax.vjp(lambda Z, theta, params: stagewise.residuals(rebuild(params), Z, theta).cost,
                           solution.Z, solution.theta, params)
    cz, ct, cp = cost_pull(solution_bar.objective)
    values, structure, diagnostics = _pullback(nlp, solution, solution_bar.Z + cz, solution_bar.theta + ct,
                                               solution_bar.multipliers, sensitivity)
    values = [a + b for a, b in zip(values, cp)]
    if sensitivity.strict:
        ok = diagnostics.reliable(sensitivity.max_residual)
        values = [jnp.where(ok, v, jnp.nan) for v in values]
    return (_cotangent(structure, values), _zero_cotangent(Z0), _zero_cotangent(theta0),
            _zero_cotangent(multipliers), _zero_cotangent(bound_multipliers))


_differentiable.defvjp(_forward, _backward)
