"""The stage-wise NLP format shared by the transcription and the solver (nothing robotic here).

    minimise    Σ_k φ(z_k, θ, d_k) + ψ(θ)
    subject to  e(z_k, θ) = 0                      k = 0..K−1   (path equalities)
                t(z_k, z_{k+1}, θ) = 0             k = 0..K−2   (transition equalities)
                l_g ≤ g(z_k, θ) ≤ u_g              k = 0..K−1   (path inequalities)
                l_h ≤ h(z_k, z_{k+1}, θ) ≤ u_h     k = 0..K−2   (transition inequalities)
                z_lo[k] ≤ z_k ≤ z_hi[k],  θ_lo ≤ θ ≤ θ_hi       (boxes)

z_k (nz,) are the knot variables, θ (ng,) the global ones, d_k per-knot data. Every function
also takes ``args``, a pytree of parameters (differentiable). Each function touches at most two
consecutive knots, so Jacobians and Hessians are block-banded; ``blocks`` computes the blocks
with ``jax.jacfwd`` vmapped over the knots.
"""

import dataclasses
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class StagewiseFunctions:
    """The callables of a stage-wise NLP (static, hashable: module-level functions).

    knot_cost(args, z, θ, d) → (); global_cost(args, θ) → (); path_equality(args, z, θ) → (me,);
    transition_equality(args, z, z_next, θ) → (mt,); path_inequality(args, z, θ) → (mg,);
    transition_inequality(args, z, z_next, θ) → (mh,).
    path_hessian (optional): (args, z, θ, y_e (me,), y_g (mg,), linearisation) → (nz + ng, nz + ng),
    the Hessian of y_e·e + y_g·g w.r.t. (z, θ), for NLPs that know a faster way than
    ``jax.hessian``; linearisation: what ``path_jacobian`` returned at (z, θ), or None (then
    the function computes what it needs itself);
    knot_cost_derivatives (optional): (args, z, θ, d) → ((∂φ/∂z (nz,), ∂φ/∂θ (ng,)),
    (∂²φ/∂z² (nz, nz), or a ``KnotHessian`` where it is mostly diagonal, ∂²φ/∂z∂θ (nz, ng),
    ∂²φ/∂θ² (ng, ng))), the knot cost's gradient and Hessian from one pass, likewise;
    transition_curvature_columns (optional): (args) → the columns of (z_k, z_{k+1}) (a tuple of
    ints in 0..2 nz − 1, static: from args' static fields) in which the transition functions
    are nonlinear for a fixed θ; they must be linear in every other entry. The solver then
    takes their Hessian over those columns alone (and θ's rows by forward-over-reverse);
    transition_through_columns (optional): (args) → None, or a subset of those columns (static)
    such that every second derivative between two curvature columns outside it is zero (the
    functions are jointly affine in the others, for a fixed θ): the Hessian then takes tangents
    along the subset alone and fills the other rows by symmetry;
    path_jacobian (optional): (args, z, θ[, y_e, y_g]) → ((∂e/∂z, ∂e/∂θ), (∂g/∂z, ∂g/∂θ),
    linearisation): both path functions' Jacobians from one pass, plus a pytree of what the path
    Hessian can reuse at the same point (on a robot: the kinematics and their Jacobian, which the
    Hessian's chain rule needs again), handed to ``path_hessian`` by the solver; given the path
    multipliers it may also hold what the path Hessian needs at those multipliers (on a robot:
    the kinematics' curvature, from the same pass as their Jacobian), and ``path_hessian`` must
    then be called with the same multipliers;
    transition_inequality_jacobian (optional): (args, z, z_next, θ) → (∂h/∂z (mh, nz),
    ∂h/∂z_next (mh, nz), ∂h/∂θ (mh, ng)), or None (static: from args' static fields) for
    ``jax.jacfwd``'s; for NLPs whose inequalities reach a costly part through few columns;
    row_supports (optional): (args) → {group: tuple of ``RowSupport``}, for each of the four
    constraint groups ("path_equality", …) a partition of its rows into consecutive runs with the
    columns of z_k (and z_{k+1}) they can depend on: the Jacobians' sparsity pattern, static
    (from args' static fields only). The solver forms its Gram products Jᵀ W J on those columns
    alone; a pattern that misses a non-zero gives a wrong Newton matrix.
    """

    knot_cost: Callable
    global_cost: Callable
    path_equality: Callable
    transition_equality: Callable
    path_inequality: Callable
    transition_inequality: Callable
    path_hessian: Callable | None = None
    knot_cost_derivatives: Callable | None = None
    transition_curvature_columns: Callable | None = None
    transition_through_columns: Callable | None = None
    transition_inequality_jacobian: Callable | None = None
    row_supports: Callable | None = None
    path_jacobian: Callable | None = None


@dataclasses.dataclass(frozen=True)
class RowSupport:
    """Rows start:stop of a constraint group depend on z_k only through the columns ``now`` and
    (transition rows) on z_{k+1} only through ``next``; tuples of ints (static, hashable)."""

    start: int
    stop: int
    now: tuple
    next: tuple = ()


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class StagewiseNLP:
    """A stage-wise NLP instance: parameters, per-knot data, bounds, and its functions.

    args: parameter pytree; knot_data: (K, ...) per-knot data d_k; z_lower, z_upper: (K, nz);
    theta_lower, theta_upper: (ng,); path_lower, path_upper: (mg,) bounds of g (same at every
    knot); transition_lower, transition_upper: (mh,) bounds of h; path_relaxation (mg,),
    transition_relaxation (mh,): which bound of each inequality row the solver's relaxation
    homotopy (``Options.relaxation``) widens: +1 the upper, −1 the lower, 0 none (None: none
    anywhere). Complementarity rows are the ones to mark (Scholtes' relaxation).
    """

    args: Any
    knot_data: jax.Array
    z_lower: jax.Array
    z_upper: jax.Array
    theta_lower: jax.Array
    theta_upper: jax.Array
    path_lower: jax.Array
    path_upper: jax.Array
    transition_lower: jax.Array
    transition_upper: jax.Array
    functions: StagewiseFunctions = dataclasses.field(metadata=dict(static=True))
    path_relaxation: jax.Array | None = None
    transition_relaxation: jax.Array | None = None

    @property
    def n_knots(self):
        return self.z_lower.shape[0]

    @property
    def knot_size(self):
        return self.z_lower.shape[1]

    @property
    def global_size(self):
        return self.theta_lower.shape[0]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Residuals:
    """Values of every function at (Z, θ): cost (), path (K, ·), transition (K − 1, ·)."""

    cost: jax.Array
    path_equality: jax.Array
    transition_equality: jax.Array
    path_inequality: jax.Array
    transition_inequality: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class KnotHessian:
    """Knot Hessian blocks diag(d_k) + E H_k Eᵀ: a diagonal (..., n) and a dense block
    (..., c, c) on the static ``columns`` (c of a knot's n variables; E their columns of the
    identity). A weighted sum of squares of single entries plus terms in a few of them (iRonCub's
    knot cost, eq. 32: the squares and the base quaternion's SO(3) log, 4 columns) is held
    without a dense (n, n) block per knot, and added into the Newton blocks where it is non-zero."""

    diagonal: jax.Array
    block: jax.Array
    columns: tuple = dataclasses.field(metadata=dict(static=True))

    @classmethod
    def of(cls, hessian):
        """A dense (..., n, n) Hessian as a ``KnotHessian`` (its block on every column)."""
        n = hessian.shape[-1]
        return cls(jnp.zeros(hessian.shape[:-1], hessian.dtype), hessian, tuple(range(n)))

    def _everywhere(self):
        return self.columns == tuple(range(self.diagonal.shape[-1]))

    def dense(self):
        """The blocks (..., n, n)."""
        n = self.diagonal.shape[-1]
        return self.added_to(jnp.zeros(self.diagonal.shape + (n,), self.diagonal.dtype), 1.0)

    def added_to(self, D, scale):
        """D + scale · these blocks, for D (..., n, n): written into D's diagonal and the block's
        entries alone."""
        n = D.shape[-1]
        diagonal = jnp.arange(n)
        D = D.at[..., diagonal, diagonal].add(scale * self.diagonal)
        if self._everywhere():
            return D + scale * self.block
        c = np.asarray(self.columns, dtype=int)
        return D.at[..., c[:, None], c[None, :]].add(scale * self.block)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Blocks:
    """First and second derivatives in block form (K knots, nz knot size, ng globals).

    cost_z (K, nz), cost_theta (ng,): cost gradient; cost_zz (a ``KnotHessian`` of K blocks
    nz × nz), cost_ztheta (K, nz, ng), cost_thetatheta (ng, ng): cost Hessian (the cost is
    knot-separable);
    for a path function p: p_z (K, m, nz), p_theta (K, m, ng); for a transition function t:
    t_z (K − 1, m, nz) w.r.t. z_k, t_znext (K − 1, m, nz) w.r.t. z_{k+1}, t_theta (K − 1, m, ng);
    path_linearisation: ``StagewiseFunctions.path_jacobian``'s reusable part per knot (leading
    axis K), for ``constraint_curvature`` at the same point; None without that function.
    """

    cost_z: jax.Array
    cost_theta: jax.Array
    cost_zz: KnotHessian
    cost_ztheta: jax.Array
    cost_thetatheta: jax.Array
    path_equality_z: jax.Array
    path_equality_theta: jax.Array
    transition_equality_z: jax.Array
    transition_equality_znext: jax.Array
    transition_equality_theta: jax.Array
    path_inequality_z: jax.Array
    path_inequality_theta: jax.Array
    transition_inequality_z: jax.Array
    transition_inequality_znext: jax.Array
    transition_inequality_theta: jax.Array
    path_linearisation: Any = None


def residuals(nlp, Z, theta):
    """Every function of the NLP at (Z (K, nz), θ (ng,)): a ``Residuals``."""
    f, a = nlp.functions, nlp.args
    path = lambda fn: jax.vmap(fn, in_axes=(None, 0, None))(a, Z, theta)  # noqa: E731
    transition = lambda fn: jax.vmap(fn, in_axes=(None, 0, 0, None))(a, Z[:-1], Z[1:], theta)  # noqa: E731
    knot_costs = jax.vmap(f.knot_cost, in_axes=(None, 0, None, 0))(a, Z, theta, nlp.knot_data)
    return Residuals(
        cost=jnp.sum(knot_costs) + f.global_cost(a, theta),
        path_equality=path(f.path_equality),
        transition_equality=transition(f.transition_equality),
        path_inequality=path(f.path_inequality),
        transition_inequality=transition(f.transition_inequality),
    )


def blocks(nlp, Z, theta, path_multipliers=None):
    """Block Jacobians of every constraint and the cost's gradient and Hessian blocks.

    Per-knot ``jax.jacfwd`` vmapped over the knots: no dense Jacobian is ever formed. The
    path equalities and inequalities come from ``StagewiseFunctions.path_jacobian`` when given
    (one pass for both, and what the path Hessian can reuse kept in ``path_linearisation``).
    path_multipliers (optional): (y_e (K, me), y_g (K, mg)), handed to ``path_jacobian`` so that
    ``path_linearisation`` may hold the path Hessian's costly part at them: then
    ``constraint_curvature`` must get the same path multipliers.
    """
    f, a = nlp.functions, nlp.args
    y = () if path_multipliers is None else tuple(path_multipliers)

    def path_jacobian(args, z, theta, *y):
        if f.path_jacobian is not None:
            return f.path_jacobian(args, z, theta, *y)
        e_z, e_theta = jax.jacfwd(f.path_equality, argnums=(1, 2))(args, z, theta)
        g_z, g_theta = jax.jacfwd(f.path_inequality, argnums=(1, 2))(args, z, theta)
        return (e_z, e_theta), (g_z, g_theta), None

    def transition(fn, jacobian=None):
        def one(args, z, z_next, theta):
            given = None if jacobian is None else jacobian(args, z, z_next, theta)
            return jax.jacfwd(fn, argnums=(1, 2, 3))(args, z, z_next, theta) if given is None else given

        return jax.vmap(one, in_axes=(None, 0, 0, None))(a, Z[:-1], Z[1:], theta)

    def knot_cost_derivatives(args, z, theta, d):
        if f.knot_cost_derivatives is not None:
            return f.knot_cost_derivatives(args, z, theta, d)
        def gradient(z, theta):
            g = jax.grad(f.knot_cost, argnums=(1, 2))(args, z, theta, d)
            return g, g  # the Jacobian's primal is the gradient itself

        ((zz, ztheta), (_, thetatheta)), g = jax.jacfwd(gradient, argnums=(0, 1), has_aux=True)(z, theta)
        return g, (zz, ztheta, thetatheta)

    (cost_z, cost_theta), (cost_zz, cost_ztheta, cost_thetatheta) = jax.vmap(
        knot_cost_derivatives, in_axes=(None, 0, None, 0))(a, Z, theta, nlp.knot_data)
    cost_zz = cost_zz if isinstance(cost_zz, KnotHessian) else KnotHessian.of(cost_zz)
    global_grad = jax.grad(f.global_cost, argnums=1)
    (pe_z, pe_theta), (pi_z, pi_theta), linearisation = jax.vmap(path_jacobian, in_axes=(None, 0, None) + (0,) * len(y))(
        a, Z, theta, *y)
    te_z, te_znext, te_theta = transition(f.transition_equality)
    ti_z, ti_znext, ti_theta = transition(f.transition_inequality, f.transition_inequality_jacobian)
    return Blocks(
        cost_z=cost_z,
        cost_theta=jnp.sum(cost_theta, axis=0) + global_grad(a, theta),
        cost_zz=cost_zz,
        cost_ztheta=cost_ztheta,
        cost_thetatheta=jnp.sum(cost_thetatheta, axis=0) + jax.hessian(f.global_cost, argnums=1)(a, theta),
        path_equality_z=pe_z,
        path_equality_theta=pe_theta,
        transition_equality_z=te_z,
        transition_equality_znext=te_znext,
        transition_equality_theta=te_theta,
        path_inequality_z=pi_z,
        path_inequality_theta=pi_theta,
        transition_inequality_z=ti_z,
        transition_inequality_znext=ti_znext,
        transition_inequality_theta=ti_theta,
        path_linearisation=linearisation,
    )


def row_supports(nlp):
    """{group: tuple of ``RowSupport``} from ``StagewiseFunctions.row_supports`` ({} without it)."""
    f = nlp.functions.row_supports
    return {} if f is None else dict(f(nlp.args))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Coupling:
    """Sub-diagonal blocks L_k = ∂²/∂z_{k+1}∂z_k (k < K − 1) non-zero only at ``rows`` (of z_{k+1})
    × ``columns`` (of z_k), static index tuples into a knot of ``size`` variables: values
    (K − 1, r, c). Applied to vectors as they are (``below``, ``above``), not as (K − 1, nz, nz)
    blocks (``dense``): on iRonCub the transition rows are curved in 47 of the 356 columns of
    (z_k, z_{k+1}), and the blocks are 19 × 28."""

    values: jax.Array
    rows: tuple = dataclasses.field(metadata=dict(static=True))
    columns: tuple = dataclasses.field(metadata=dict(static=True))
    size: int = dataclasses.field(metadata=dict(static=True))

    def _indices(self):
        return np.asarray(self.rows, dtype=int), np.asarray(self.columns, dtype=int)

    def dense(self):
        """The blocks (K − 1, size, size)."""
        r, c = self._indices()
        blocks = jnp.zeros(self.values.shape[:1] + (self.size, self.size), self.values.dtype)
        return blocks.at[:, r[:, None], c[None, :]].set(self.values)

    def below(self, x):
        """L_k x_k for x (K, size): (K − 1, size)."""
        r, c = self._indices()
        product = jnp.einsum("krc,kc->kr", self.values, x[:-1][:, c])
        return jnp.zeros((x.shape[0] - 1, self.size), x.dtype).at[:, r].set(product)

    def above(self, x):
        """L_kᵀ x_{k+1} for x (K, size): (K − 1, size)."""
        r, c = self._indices()
        product = jnp.einsum("krc,kr->kc", self.values, x[1:][:, r])
        return jnp.zeros((x.shape[0] - 1, self.size), x.dtype).at[:, c].set(product)


def _curvature_columns(nlp, nz):
    """The transition functions' curvature columns of (z_k, z_{k+1}) (0..2 nz − 1), checked."""
    f = nlp.functions
    columns = (np.arange(2 * nz) if f.transition_curvature_columns is None
               else np.asarray(f.transition_curvature_columns(nlp.args), dtype=int).reshape(-1))
    if columns.size != np.unique(columns).size or (columns.size and (columns.min() < 0 or columns.max() >= 2 * nz)):
        raise ValueError(f"transition_curvature_columns must be distinct columns in 0..{2 * nz - 1}, "
                         f"got {columns.tolist()}")
    return columns


def _coupling_pattern(columns, nz):
    """(rows of z_{k+1}, columns of z_k) of the coupling blocks, from the curvature columns."""
    return tuple(int(c) - nz for c in columns[columns >= nz]), tuple(int(c) for c in columns[columns < nz])


def zero_coupling(nlp, K, nz, dtype):
    """A zero ``Coupling`` of the structure ``constraint_curvature(…, compact=True)`` returns."""
    rows, cols = _coupling_pattern(_curvature_columns(nlp, nz), nz)
    return Coupling(jnp.zeros((K - 1, len(rows), len(cols)), dtype), rows, cols, nz)


def constraint_curvature(nlp, Z, theta, path_equality, transition_equality, path_inequality, transition_inequality,
                         path_linearisation=None, compact=False):
    """Blocks of Σ yᵢ ∇²cᵢ for the given multipliers (shaped like ``Residuals``' constraints);
    path_linearisation: ``Blocks.path_linearisation`` at the same (Z, θ), for the NLP's
    ``path_hessian`` to reuse (None: it computes what it needs).

    Returns (D (K, nz, nz) diagonal blocks, L (K − 1, nz, nz) sub-diagonal blocks ∂²/∂z_{k+1}∂z_k,
    B (K, nz, ng) knot–global blocks, C (ng, ng)); with ``compact``, L as a ``Coupling`` on the
    transition curvature columns.
    """
    f, a = nlp.functions, nlp.args
    K, nz = Z.shape
    columns = _curvature_columns(nlp, nz)

    through = None if f.transition_through_columns is None else f.transition_through_columns(a)
    if through is not None:
        through = np.asarray(through, dtype=int).reshape(-1)
        if not np.all(np.isin(through, columns)) or through.size != np.unique(through).size:
            raise ValueError("transition_through_columns must be distinct transition_curvature_columns")
        through = np.flatnonzero(np.isin(columns, through))  # positions among the columns

    def path_hessian(args, z, theta, y_e, y_g, linearisation):
        def weighted(w):
            return jnp.sum(f.path_equality(args, w[:nz], w[nz:]) * y_e) + jnp.sum(
                f.path_inequality(args, w[:nz], w[nz:]) * y_g
            )

        return jax.hessian(weighted)(jnp.concatenate([z, theta]))

    hessian = path_hessian if f.path_hessian is None else f.path_hessian
    H = jax.vmap(hessian, in_axes=(None, 0, None, 0, 0, None if path_linearisation is None else 0))(
        a, Z, theta, path_equality, path_inequality, path_linearisation)
    D, B, C = H[:, :nz, :nz], H[:, :nz, nz:], jnp.sum(H[:, nz:, nz:], axis=0)
    interval = functools.partial(_transition_curvature, f, columns=columns, through=through)
    inner, mixed, corner = jax.vmap(interval, in_axes=(None, 0, 0, None, 0, 0))(
        a, Z[:-1], Z[1:], theta, transition_equality, transition_inequality)
    # Only the nonlinear columns' entries are scattered: the dense (2 nz + ng)² Hessian of
    # every interval cost more to fill and slice than to compute.
    now, following = columns < nz, columns >= nz
    cn, cf = columns[now], columns[following] - nz
    inner_now = inner[:, now][:, :, now]
    inner_next = inner[:, following][:, :, following]
    D = D.at[:-1, cn[:, None], cn[None, :]].add(inner_now).at[1:, cf[:, None], cf[None, :]].add(inner_next)
    L = Coupling(inner[:, following][:, :, now], *_coupling_pattern(columns, nz), nz)
    B = B + _before(mixed[:, :nz]) + _after(mixed[:, nz:])
    return D, L if compact else L.dense(), B, C + jnp.sum(corner, axis=0)


def _transition_curvature(functions, args, z, z_next, theta, y_t, y_h, columns, through=None):
    """One interval's Σ y ∇²(t, h): the Hessian over ``columns`` of (z, z_next) (c, c), the
    mixed block ∂²/∂(z, z_next)∂θ (2 nz, ng) and ∂²/∂θ² (ng, ng). through: None, or the
    positions among ``columns`` whose tangents the Hessian needs (the functions are jointly affine
    in the others): their rows by forward over reverse, the others' rows by symmetry."""
    nz = z.shape[0]

    def weighted(w, th):
        now, nxt = w[:nz], w[nz:]
        return jnp.dot(y_t, functions.transition_equality(args, now, nxt, th)) + jnp.dot(
            y_h, functions.transition_inequality(args, now, nxt, th))

    w0 = jnp.concatenate([z, z_next])
    if through is None:
        inner = jax.hessian(lambda v: weighted(w0.at[columns].set(v), theta))(w0[columns])
    else:
        gradient = jax.grad(lambda v: weighted(w0.at[columns].set(v), theta))
        v0 = w0[columns]
        tangents = jnp.eye(columns.size, dtype=w0.dtype)[through]
        across = jax.vmap(lambda e: jax.jvp(gradient, (v0,), (e,))[1])(tangents)  # rows ``through``
        others = np.setdiff1d(np.arange(columns.size), through)
        inner = jnp.zeros((columns.size, columns.size), w0.dtype).at[through].set(across)
        inner = inner.at[others[:, None], through[None, :]].set(across[:, others].T)
    mixed, corner = jax.jacfwd(lambda th: jax.grad(weighted, argnums=(0, 1))(w0, th))(theta)
    return inner, mixed, corner


def _before(blocks):
    """Per-interval blocks (K − 1, …) as per-knot blocks (K, …) of each interval's first knot."""
    return jnp.concatenate([blocks, jnp.zeros_like(blocks[:1])])


def _after(blocks):
    """Per-interval blocks (K − 1, …) as per-knot blocks (K, …) of each interval's last knot."""
    return jnp.concatenate([jnp.zeros_like(blocks[:1]), blocks])
