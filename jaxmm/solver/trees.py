"""Arithmetic on the solver's tuples of arrays (the primal leaves (Z, θ, path slacks, transition
slacks), the four constraint groups' multipliers, …)."""

import jax
import jax.numpy as jnp


def tmap(fn, *trees):
    """(fn(a₀, b₀, …), fn(a₁, b₁, …), …) over tuples of the same length."""
    return tuple(fn(*leaves) for leaves in zip(*trees))


def dot(a, b):
    """Σ over the leaves of Σ aᵢ bᵢ."""
    return sum(jnp.sum(x * y) for x, y in zip(a, b))


def max_abs(tree):
    """The largest |entry| over the leaves (0 for empty leaves)."""
    return jnp.max(jnp.stack([jnp.max(jnp.abs(leaf), initial=0.0) for leaf in tree]))


def l1(tree):
    """Σ |entries| over the leaves."""
    return sum(jnp.sum(jnp.abs(v)) for v in tree)


def select(flag, a, b):
    """a where the traced boolean ``flag`` holds, else b, leaf by leaf (pytrees of one structure)."""
    return jax.tree.map(lambda x, y: jnp.where(flag, x, y), a, b)


def zeros_like(tree):
    """Zeros of the structure, shapes and dtypes of ``tree`` (arrays or ``jax.ShapeDtypeStruct``s)."""
    return jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), tree)
