"""The model problem of a bound-constrained inner iteration: a QP with a bordered
block-tridiagonal Hessian, plus penalised linearised inequality rows, over a box.

    minimise  gᵀd + ½ dᵀ H d + Σᵢ ρᵢ/2 dist(aᵢ + Jᵢ d, [lᵢ, uᵢ])²   subject to  lo ≤ d ≤ hi

(lo ≤ 0 ≤ hi). The penalty rows are the inequalities of an augmented Lagrangian in projection
form (aᵢ = gᵢ + yᵢ/ρᵢ): with slack variables sᵢ ∈ [lᵢ, uᵢ] eliminated, as LANCELOT treats
inequalities. Keeping them as rows of the model, rather than freezing their activity at the
current point, lets the step see a row that its own move would switch on (a friction cone or a
complementarity row a step would violate) instead of walking into it and being cut short by the
line search.

Solved by semismooth projected Newton (Bertsekas 1982; the box-QP of Tassa et al. 2014): at each
iteration the variables at a bound whose gradient points outwards are clamped, the rows outside
their interval are active, the free variables take the Newton step of that reduced model, and a
projected Armijo search keeps d in the box. Unlike one projected-Newton step with the active set
read off the first gradient, the iterations release a bound when the coupling with the other
variables makes moving off it pay: a jet at zero thrust spins up because the model says the
final CoM needs it, not because its own gradient does.
"""

import dataclasses

import jax
import jax.numpy as jnp

from jaxmm.solver import linalg, rows as rows_


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PenaltyRows:
    """ρ/2 dist(a + J d, [lower, upper])² per row: ``rows`` (``rows.Rows``) holds J, ``shifted``
    (R, m) is a, ``penalty`` (R, m) is ρ, ``lower``/``upper`` (m,) the interval."""

    rows: rows_.Rows
    shifted: jax.Array
    penalty: jax.Array
    lower: jax.Array
    upper: jax.Array


def excess(p, d=None):
    """r − Π_[l,u](r) of ``PenaltyRows`` p at r = a + J d (d = None: at d = 0); nonzero on the
    active rows. ρ · excess is the rows' multiplier estimate."""
    r = p.shifted if d is None else p.shifted + rows_.apply(p.rows, *d)
    return r - jnp.clip(r, p.lower, p.upper)


def solve(hessian, g, lo, hi, iterations, penalties=(), search_steps=20):
    """Approximately solve the model problem.

    hessian: (D (K, n, n), L (K − 1, n, n), B (K, n, m), C (m, m)), positive definite;
    g, lo, hi: pairs ((K, n), (m,)) of the gradient and the bounds on d; penalties: a tuple of
    ``PenaltyRows``. Returns ((dz, dt), ok) with ok False when a reduced Hessian could not be
    factored.
    """
    D, L, B, C = hessian
    K = D.shape[0]

    def value(d):
        hz, ht = linalg.matvec(D, L, B, C, *d)
        quadratic = sum(jnp.sum(gi * di) + 0.5 * jnp.sum(di * hi_) for gi, di, hi_ in zip(g, d, (hz, ht)))
        return quadratic + sum(0.5 * jnp.sum(p.penalty * excess(p, d) ** 2) for p in penalties)

    def gradient(d):
        hz, ht = linalg.matvec(D, L, B, C, *d)
        gz, gt = g[0] + hz, g[1] + ht
        for p in penalties:
            pz, pt = rows_.pull(p.rows, p.penalty * excess(p, d), K)
            gz, gt = gz + pz, gt + pt
        return gz, gt

    def activity(d):
        return tuple(excess(p, d) != 0 for p in penalties)

    def project(d):
        return tuple(jnp.clip(di, l, h) for di, l, h in zip(d, lo, hi))

    def free(d, grad):
        return tuple(
            (~(((di <= l) & (gi > 0)) | ((di >= h) & (gi < 0)) | (l == h))).astype(di.dtype)
            for di, gi, l, h in zip(d, grad, lo, hi)
        )

    def iteration(carry):
        d, _, count, ok, _ = carry
        grad = gradient(d)
        fz, ft = free(d, grad)
        active = activity(d)
        Dm, Lm, Bm, Cm = rows_.add(
            (D, L, B, C),
            *(rows_.gram(p.rows, p.penalty * a, K) for p, a in zip(penalties, active)),
        )
        chol = linalg.factor(
            fz[:, :, None] * Dm * fz[:, None, :] + jax.vmap(jnp.diag)(1.0 - fz),
            fz[1:, :, None] * Lm * fz[:-1, None, :],
            fz[:, :, None] * Bm * ft[None, None, :],
            ft[:, None] * Cm * ft[None, :] + jnp.diag(1.0 - ft),
        )
        sz, st = linalg.solve(chol, -grad[0] * fz, -grad[1] * ft)
        step = (sz * fz, st * ft)
        base = value(d)

        def trial(beta):
            candidate = project(tuple(di + beta * si for di, si in zip(d, step)))
            decrease = sum(jnp.sum(gi * (ci - di)) for gi, ci, di in zip(grad, candidate, d))
            return candidate, value(candidate), decrease

        def shorter(search):
            beta, _, _, _, n = search
            return (beta * 0.5, *trial(beta * 0.5), n + 1)

        def insufficient(search):
            _, _, v, decrease, n = search
            return (v > base + 1e-4 * decrease) & (n < search_steps)

        beta, candidate, v, _, n = jax.lax.while_loop(insufficient, shorter, (1.0, *trial(1.0), 0))
        accepted = chol.ok & (n < search_steps) & jnp.isfinite(v)
        d_new = jax.tree.map(lambda c, o: jnp.where(accepted, c, o), candidate, d)
        # Done when a full step was taken on unchanged free and active sets (the reduced model,
        # a plain QP, is then solved exactly).
        f_new = free(d_new, gradient(d_new))
        same = jnp.all(f_new[0] == fz) & jnp.all(f_new[1] == ft)
        for before, after in zip(active, activity(d_new)):
            same = same & jnp.all(before == after)
        done = (~accepted) | (same & (beta == 1.0))
        return d_new, done, count + 1, ok & chol.ok, beta

    def running(carry):
        _, done, count, ok, _ = carry
        return (~done) & (count < iterations) & ok

    zero = (jnp.zeros_like(g[0]), jnp.zeros_like(g[1]))
    start = (project(zero), jnp.asarray(False), jnp.asarray(0), jnp.asarray(True), jnp.asarray(1.0, g[0].dtype))
    d, _, _, ok, _ = jax.lax.while_loop(running, iteration, start)
    return d, ok
