"""``jaxmm.compilation.jit``: jaxmm's programs compiled with its XLA options, usable anywhere
``jax.jit`` is."""

import jax
import jax.numpy as jnp
import numpy as np

import jaxmm
from jaxmm import compilation


def _poses(model, Q):
    return jax.vmap(lambda q: jaxmm.body_poses(model, q))(Q)


def _configurations(model, count=71):
    Q = 0.3 * jax.random.normal(jax.random.key(0), (count, 7 + model.n_joints))
    return Q.at[:, 3:7].add(jnp.array([0.0, 0.0, 0.0, 1.0]))


def test_top_level_programs_compile_with_the_options_and_agree_with_jax_jit():
    model = jaxmm.load_ironcub().model
    Q = _configurations(model)
    options = compilation.compiler_options()
    assert options in ({}, {"xla_cpu_experimental_ynn_fusion_type": ""})
    tuned = compilation.jit(_poses)
    plain_text = jax.jit(_poses).lower(model, Q).compile().as_text()
    tuned_text = tuned.lower(model, Q).compile().as_text()
    if options and jax.default_backend() == "cpu" and "__ynn_fusion" in plain_text:
        assert "__ynn_fusion" not in tuned_text  # the option reached the compiler
    for a, b in zip(jax.tree.leaves(tuned(model, Q)), jax.tree.leaves(jax.jit(_poses)(model, Q))):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)


def test_nested_in_other_transformations():
    """Inside another jit, vmap, grad or eval_shape the function is traced as a plain jit (JAX
    takes compiler options from the outermost jit only)."""

    @compilation.jit(static_argnames="power")
    def f(x, power):
        """x to the power."""
        return jnp.sum(x**power)

    x = jnp.arange(1.0, 4.0)
    assert float(f(x, 2)) == 14.0
    assert float(jax.jit(lambda x: f(x, 3))(x)) == 36.0
    np.testing.assert_array_equal(jax.vmap(lambda v: f(v, 2))(x[:, None]), x**2)
    np.testing.assert_array_equal(jax.grad(lambda x: f(x, 2))(x), 2 * x)
    assert jax.eval_shape(lambda x: f(x, 2), x).shape == ()
    assert f.__doc__ == "x to the power." and f.__name__ == "f"
    assert f._cache_size() == 1  # what jax.jit offers is there (lower, _cache_size, …)
