"""Arithmetic on the solver's tuples of arrays (the primal leaves (Z, θ, path slacks, transition
slacks), the four constraint groups' multipliers, …)."""

import jax
import jax.numpy as jnp


def tmap(fn, *trees):
    """(fn(a₀, b₀, …), fn(a₁, b₁, …), …) over tuples of the same length."""
    return tuple(fn(*leaves) for leaves in zip(*trees))


def flat(tree):
    """Every entry of the leaves in one vector. A reduction over it is one kernel (two above
    32 entries: XLA's CPU tree-reduction rewrite), where a reduction per leaf is one each."""
    return jnp.concatenate([jnp.ravel(leaf) for leaf in jax.tree.leaves(tree)])


def dot(a, b):
    """Σ over the leaves of Σ aᵢ bᵢ."""
    return jnp.sum(flat(tmap(jnp.multiply, a, b)))


def max_abs(tree):
    """The largest |entry| over the leaves (0 for empty leaves)."""
    return jnp.max(jnp.abs(flat(tree)), initial=0.0)


def l1(tree):
    """Σ |entries| over the leaves."""
    return jnp.sum(jnp.abs(flat(tree)))


def all_finite(tree):
    """Whether every entry of every leaf is finite."""
    return jnp.all(jnp.isfinite(flat(tree)))


def select(flag, a, b):
    """a where the traced boolean ``flag`` holds, else b (pytrees of one structure, both already
    computed). A conditional that passes one of them through compiles to buffer copies, where
    an element-wise select per leaf compiles a kernel per leaf (and XLA's CPU backend spends
    ≈ 20 ms compiling even a trivial kernel); under ``vmap`` a batched flag makes it a select."""
    return jax.lax.cond(flag, lambda: a, lambda: b)


def zeros_like(tree):
    """Zeros of the structure, shapes and dtypes of ``tree`` (arrays or ``jax.ShapeDtypeStruct``s)."""
    return jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), tree)
