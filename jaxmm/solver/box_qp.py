"""Box-constrained QPs with a bordered block-tridiagonal Hessian: the Newton step of a
bound-constrained inner iteration.

    minimise  gᵀd + ½ dᵀ H d   subject to  lo ≤ d ≤ hi      (lo ≤ 0 ≤ hi)

by projected Newton (Bertsekas 1982; the box-QP of Tassa et al. 2014): at each iteration the
variables at a bound whose gradient points outwards are clamped, the free ones take the
Newton step of the reduced QP, and a projected Armijo search keeps d in the box. Unlike a
single projected-Newton step with the active set read off the first gradient, the iterations
release a bound when the coupling with the other variables makes moving off it pay: a jet at
zero thrust spins up because the QP says the final CoM needs it, not because its own gradient
does.
"""

import jax
import jax.numpy as jnp

from jaxmm.solver import linalg


def solve(hessian, g, lo, hi, iterations, search_steps=20):
    """Approximately solve the box QP.

    hessian: (D (K, n, n), L (K − 1, n, n), B (K, n, m), C (m, m)), positive definite;
    g, lo, hi: pairs ((K, n), (m,)) of the gradient and the bounds on d. Returns
    ((dz, dt), ok) with ok False when a reduced Hessian could not be factored.
    """
    D, L, B, C = hessian

    def value(d):
        hz, ht = linalg.matvec(D, L, B, C, *d)
        return sum(jnp.sum(gi * di) + 0.5 * jnp.sum(di * hi_) for gi, di, hi_ in zip(g, d, (hz, ht)))

    def gradient(d):
        hz, ht = linalg.matvec(D, L, B, C, *d)
        return g[0] + hz, g[1] + ht

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
        chol = linalg.factor(
            fz[:, :, None] * D * fz[:, None, :] + jax.vmap(jnp.diag)(1.0 - fz),
            fz[1:, :, None] * L * fz[:-1, None, :],
            fz[:, :, None] * B * ft[None, None, :],
            ft[:, None] * C * ft[None, :] + jnp.diag(1.0 - ft),
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
        # Done when a full step was taken on an unchanged free set (the reduced QP is solved).
        f_new = free(d_new, gradient(d_new))
        same = jnp.all(f_new[0] == fz) & jnp.all(f_new[1] == ft)
        done = (~accepted) | (same & (beta == 1.0))
        return d_new, done, count + 1, ok & chol.ok, beta

    def running(carry):
        _, done, count, ok, _ = carry
        return (~done) & (count < iterations) & ok

    zero = (jnp.zeros_like(g[0]), jnp.zeros_like(g[1]))
    start = (project(zero), jnp.asarray(False), jnp.asarray(0), jnp.asarray(True), jnp.asarray(1.0, g[0].dtype))
    d, _, _, ok, _ = jax.lax.while_loop(running, iteration, start)
    return d, ok
