"""The Newton system of one interior-point iteration, condensed, factored and solved.

With the equality rows under the primal–dual augmented Lagrangian (Gill & Robinson 2013; penalty
ρ = 1/δ_c) and the slacks eliminated row by row, the regularised KKT system

    [ W + Σ + δ_w I   Jᵀ          ] [ dx ]     [ r_x ]
    [ J             −diag(1/w)    ] [ dλ ] = − [ r_c ]

condenses exactly onto the bordered block-tridiagonal matrix W + Σ + δ_w I + Jᵀ diag(w) J
(``rows.grams``), positive definite exactly when the inertia is right: its block Cholesky
(``linalg.factor``) is the inertia test, and δ_w grows until it succeeds (IPOPT's inertia
correction, Wächter & Biegler 2006, section 3.1). Each step is then refined towards the exact
(δ_c = 0) KKT system with the regularised factor as preconditioner. The same system, with
Gauss–Newton weights and no Lagrangian curvature, is the restoration phase's.

One factorisation call site (``factor``, the attempts of the inertia correction in one loop) and
one block-solve call site (``refined_solve``) serve every step of an iteration.
"""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmm.solver import linalg, rows
from jaxmm.solver.options import GROUPS, REFINEMENT_RATIO
from jaxmm.solver.trees import max_abs, tmap, zeros_like


def jacobian_rows(problem, B, supports):
    """The constraint rows' Jacobian blocks of ``stagewise.Blocks`` B in the solver's units
    (``scaling.ScaledProblem``), inequality rows that constrain nothing left out."""
    J = tuple(rows.scaled(rows.group_rows(B, g, supports.get(g)), s) for g, s in zip(GROUPS, problem.row_scale))
    return J[:2] + tuple(rows.scaled(r, a) for r, a in zip(J[2:], problem.active))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Masks:
    """free_z (K, nz), free_theta (ng,): 1 on the variables that are not fixed, 0 on those that
    are (equal bounds); fixed_z, fixed_theta: the complements."""

    free_z: jax.Array
    free_theta: jax.Array
    fixed_z: jax.Array
    fixed_theta: jax.Array


def masks(b, dtype):
    """``Masks`` from the primal leaves' ``barrier.Bounds``."""
    fixed_z, fixed_t = (~b.free[0]).astype(dtype), (~b.free[1]).astype(dtype)
    return Masks(1 - fixed_z, 1 - fixed_t, fixed_z, fixed_t)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class System:
    """A condensed Newton system: J, the four groups' ``rows.Rows``; weights (R, m) per group,
    each row's weight w in the condensed matrix; inv_sigma, 1/(σ_s + δ_s) per slack leaf (0 where
    a slack has no barrier); hessian, the blocks (D, L, B, C) of W (the Lagrangian's Hessian;
    zeros in the restoration phase; L may be a ``stagewise.Coupling``), masked by nothing;
    diagonal, (Σ + the regularisation) of (Z (K, nz), θ (ng,)); slack_diagonal, σ_s + δ_s per
    slack leaf; active, the inequality rows with a bound; masks, the fixed variables (``Masks``)."""

    J: tuple
    weights: tuple
    inv_sigma: tuple
    hessian: tuple
    diagonal: tuple
    slack_diagonal: tuple
    active: tuple
    masks: Masks


def attempted(chol, K):
    """Diagonal blocks a factorisation attempt factored, the indefinite one included."""
    return jnp.minimum(chol.factored + 1, K)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Correction:
    """The inertia correction's loop state: the last δ_w tried, its factor, whether it factored,
    the diagonal blocks factored over all attempts, and whether any attempt was made."""

    delta: jax.Array
    chol: linalg.BlockCholesky
    ok: jax.Array
    work: jax.Array
    tried: jax.Array


def next_regularisation(delta, last, decrease):
    """IPOPT's δ_w rule but for the decrease: from 0, the last δ_w needed (``last``; 0: none yet)
    times ``decrease`` (1e-4 with none yet), then ×8 (×100 with none yet)."""
    resumed = jnp.maximum(1e-20, last * decrease)
    return jnp.where(delta == 0.0, jnp.where(last == 0.0, 1e-4, resumed), delta * jnp.where(last == 0.0, 100.0, 8.0))


def factor(blocks_at, diagonal_at, first, grow, correct, ceiling, K, coupled=None, masks=None):
    """The inertia correction: factor ``blocks_at(δ)`` (blocks (D, L, B, C)) with the diagonal
    ``diagonal_at(δ)`` ((K, nz), (ng,)) added and the fixed variables of ``masks`` (``Masks``,
    optional) held out, from δ = first, δ ← grow(δ) while the factorisation fails, ``correct``
    holds and δ < ceiling. Every attempt runs at this one call site of ``linalg.factor`` (the
    interior-point iteration's, with ``next_regularisation``, and the sensitivity's
    preconditioner, with its own growth), each in the storage of the one before.

    Returns (δ, the factor, whether it factored, the diagonal blocks factored over all attempts)."""
    free = None if masks is None else (masks.free_z, masks.free_theta)

    def attempt(delta, into=None):
        shift, corner_shift = diagonal_at(delta)
        return linalg.factor(*blocks_at(delta), coupled=coupled, shift=shift, corner_shift=corner_shift, free=free,
                             into=into)

    def needs_more(s):
        return ~s.tried | (correct & ~s.ok & (s.delta < ceiling))

    def more(s):
        delta = jnp.where(s.tried, grow(s.delta), first)
        chol = attempt(delta, s.chol)
        return Correction(delta, chol, chol.ok, s.work + attempted(chol, K), jnp.asarray(True))

    empty = zeros_like(jax.eval_shape(attempt, first))
    s = jax.lax.while_loop(needs_more, more, Correction(jnp.asarray(first), empty, jnp.asarray(False),
                                                        jnp.zeros((), empty.factored.dtype), jnp.asarray(False)))
    return s.delta, s.chol, s.ok, s.work


def condensed_solve(chol, system, ax, a_s, a_c):
    """The regularised KKT system [W + Σ, Jᵀ; J, −diag(1/w)] with right-hand sides ax (dual rows
    of (Z, θ)), a_s (dual rows of the slacks) and a_c (constraint rows), by condensing onto
    ``chol``, the factor of W + Σ + Jᵀ diag(w) J (slacks eliminated row by row: dv = w (J dx + c_g +
    r_s / σ_s), ds = (dv − r_s) / σ_s). Returns ((dx, ds, dy), J dx per row group)."""
    J, weights, inv_sigma, m = system.J, system.weights, system.inv_sigma, system.masks
    fz, ft = m.free_z, m.free_theta
    K = fz.shape[0]
    shifts = a_c[:2] + tuple(ag + a * i for ag, a, i in zip(a_c[2:], a_s, inv_sigma))
    rz, rt = ax
    for r, w, sh in zip(J, weights, shifts):
        pz, pt = rows.pull(r, w * sh, K)
        rz, rt = rz + pz, rt + pt
    dz, dt = linalg.solve(chol, rz * fz, rt * ft)
    dz, dt = dz * fz, dt * ft
    Jdx = tuple(rows.apply(r, dz, dt) for r in J)
    dy = tuple(w * (jd - sh) for jd, w, sh in zip(Jdx, weights, shifts))
    ds = tuple((a + dv) * i for a, dv, i in zip(a_s, dy[2:], inv_sigma))
    return ((dz, dt), ds, dy), Jdx


def kkt_residual(system, ax, a_s, a_c, dx, ds, dy, Jdx):
    """Residual of the exact KKT system (δ_c = 0, the system's own Σ + δ_w and δ_s) at the step
    (dx, ds, dy), the blocks applied to vectors (the masks and the diagonal too: no copy of the
    blocks). Jdx: J dx per row group, which the caller sums over the refinement's increments
    (J is linear), so that each refinement passes over the Jacobians three times, not four."""
    J, m = system.J, system.masks
    fz, ft = m.free_z, m.free_theta
    K = fz.shape[0]
    hz, ht = linalg.matvec(*system.hessian, dx[0] * fz, dx[1] * ft)
    hz = hz * fz + (m.fixed_z + fz * system.diagonal[0]) * dx[0]
    ht = ht * ft + (m.fixed_theta + ft * system.diagonal[1]) * dx[1]
    for r, dv in zip(J, dy):
        pz, pt = rows.pull(r, dv, K)
        hz, ht = hz + pz, ht + pt
    return (
        ((ax[0] - hz) * fz, (ax[1] - ht) * ft),
        tuple(jnp.where(i > 0, a - (sd * d - dv), 0.0)
              for a, sd, d, dv, i in zip(a_s, system.slack_diagonal, ds, dy[2:], system.inv_sigma)),
        tuple(a - jd for a, jd in zip(a_c[:2], Jdx[:2]))
        + tuple(jnp.where(act, a - (jd - d), 0.0) for a, jd, d, act in zip(a_c[2:], Jdx[2:], ds, system.active)),
    )


def refined_solve(chol, system, rhs, limit):
    """The step (dx, ds, dy) for the right-hand sides rhs = (ax, a_s, a_c): ``condensed_solve``,
    then refined towards the exact KKT system while its residual falls by 10 % and stays above
    REFINEMENT_RATIO of the right-hand side, ``limit`` solves in all (traced; 0: no solve, a zero
    step). ρ JᵀJ makes the condensed matrix ill-conditioned, and δ_c alone biases the step
    enough to make the last iterations converge only linearly. Returns (step, solves)."""
    floor = REFINEMENT_RATIO * jnp.maximum(1.0, max_abs(jax.tree.leaves(rhs)))

    def improving(carry):
        k, _, _, _, size, previous = carry
        return (k < limit) & ((k == 0) | ((size > floor) & (size < 0.9 * previous)))

    def refine(carry):
        k, step, Jstep, residual, size, _ = carry
        increment, Jincrement = condensed_solve(chol, system, *residual)
        step, Jstep = jax.tree.map(jnp.add, step, increment), jax.tree.map(jnp.add, Jstep, Jincrement)
        residual = kkt_residual(system, *rhs, *step, Jstep)
        return k + 1, step, Jstep, residual, max_abs(jax.tree.leaves(residual)), jnp.where(k == 0, jnp.inf, size)

    ax, a_s, a_c = rhs
    zero = tmap(jnp.zeros_like, ax), tmap(jnp.zeros_like, a_s), tmap(jnp.zeros_like, a_c)
    size = max_abs(jax.tree.leaves(rhs))
    carry = (jnp.asarray(0), zero, zero[2], rhs, size, jnp.asarray(jnp.inf, size.dtype))
    solves, step, _, _, _, _ = jax.lax.while_loop(improving, refine, carry)
    return step, solves
