"""``jaxmm.compilation.jit``: jaxmm's programs compiled with its XLA options, usable anywhere
``jax.jit`` is."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.experimental.compilation_cache import compilation_cache

import jaxmm
from jaxmm import compilation


def _poses(model, Q):
    return jax.vmap(lambda q: jaxmm.body_poses(model, q))(Q)


def _configurations(model, count=71):
    Q = 0.3 * jax.random.normal(jax.random.key(0), (count, 7 + model.n_joints))
    return Q.at[:, 3:7].add(jnp.array([0.0, 0.0, 0.0, 1.0]))


YNN = "xla_cpu_experimental_ynn_fusion_type"
PASSES = "xla_disable_hlo_passes"


def test_top_level_programs_compile_with_the_options_and_agree_with_jax_jit():
    """Where this jaxlib knows XLA:CPU's YNNPACK option, jaxmm compiles with it set to "" (no
    YNNPACK fusions): the kinematics' batched dot, which YNNPACK takes when its dot fusions are
    asked for (whatever XLA_FLAGS say: compiler options override them), stays out of YNNPACK in
    jaxmm's program. Where jaxlib does not know it, compiling with it fails, and jaxmm passes
    no such option. Either way the results equal ``jax.jit``'s."""
    model = jaxmm.load_ironcub().model
    Q = _configurations(model)
    options = compilation.compiler_options()
    assert set(options) <= {YNN, PASSES}
    if YNN in options:
        assert options[YNN] == ""
        asked = jax.jit(_poses, compiler_options={YNN: "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}).lower(model, Q)
        assert "__ynn_fusion" in asked.compile().as_text()
        assert "__ynn_fusion" not in compilation.jit(_poses).lower(model, Q).compile().as_text()
    else:
        with pytest.raises(jax.errors.JaxRuntimeError, match=YNN):
            jax.jit(_poses, compiler_options={YNN: ""}).lower(model, Q).compile()
    tuned = compilation.jit(_poses)
    for a, b in zip(jax.tree.leaves(tuned(model, Q)), jax.tree.leaves(jax.jit(_poses)(model, Q)), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)


def test_long_reductions_compile_as_one_kernel_each():
    """XLA's tree reduction rewrite is off in jaxmm's programs: a sum over more than 32 entries
    is a reduce, not a reduce-window feeding one (a kernel more per reduction), and the sum
    agrees with ``jax.jit``'s to rounding."""
    options = compilation.compiler_options()
    assert options.get(PASSES) == "tree_reduction_rewriter"
    x = jnp.linspace(-1.0, 2.0, 5000).reshape(50, 100)

    def total(x):
        return jnp.sum(x * x, axis=1), jnp.sum(jnp.abs(x))

    rewritten = jax.jit(total, compiler_options={k: v for k, v in options.items() if k != PASSES})
    assert "reduce-window" in rewritten.lower(x).compile().as_text()
    ours = compilation.jit(total)
    assert "reduce-window" not in ours.lower(x).compile().as_text()
    for a, b in zip(ours(x), rewritten(x), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-13)


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
    assert float(f.lower(x, 2).compile()(x)) == 14.0  # what jax.jit offers is there (lower, trace, …)


@pytest.fixture
def jax_cache_settings():
    """Restores this process's persistent-cache settings (the conftest's) after the test."""
    names = ("jax_compilation_cache_dir", "jax_compilation_cache_max_size", "jax_persistent_cache_min_compile_time_secs")
    saved = {name: getattr(jax.config, name) for name in names}
    yield
    for name, value in saved.items():
        jax.config.update(name, value)
    compilation_cache.reset_cache()


def _entries(directory):
    return sorted(p.name for p in directory.iterdir() if p.name.endswith("-cache"))


def test_persistent_cache_keeps_programs_where_it_is_pointed(tmp_path, jax_cache_settings):
    first, second = tmp_path / "first", tmp_path / "second"
    assert compilation.use_persistent_cache(first, min_compile_seconds=0) == first
    np.testing.assert_allclose(jax.jit(lambda x: jnp.sin(x) * 3.25)(1.0), np.sin(1.0) * 3.25)
    kept = _entries(first)
    assert any(name.startswith("jit__lambda") for name in kept)
    assert jax.config.jax_compilation_cache_max_size > 0  # the limit that turns the file lock on
    compilation.use_persistent_cache(second, min_compile_seconds=0)  # re-pointed in the same process
    jax.jit(lambda x: jnp.cos(x) * 1.75)(1.0).block_until_ready()
    assert _entries(first) == kept
    assert any(name.startswith("jit__lambda") for name in _entries(second))
    assert not set(_entries(second)) & set(kept)


def test_persistent_cache_names_a_bad_directory(tmp_path, jax_cache_settings):
    occupied = tmp_path / "a-file"
    occupied.write_text("")
    with pytest.raises(NotADirectoryError, match="a-file exists and is not a directory"):
        compilation.use_persistent_cache(occupied)
    with pytest.raises(ValueError, match="max_size must be a positive"):
        compilation.use_persistent_cache(tmp_path, max_size=0)


def test_default_cache_directory_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.delenv("JAXMM_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert compilation.default_cache_directory() == tmp_path / "jaxmm" / "xla"
    monkeypatch.setenv("JAXMM_CACHE_DIR", str(tmp_path / "mine"))
    assert compilation.default_cache_directory() == tmp_path / "mine"


TRACES = []


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class _Scaled:
    """An argument whose static field is part of the program, not an input."""

    x: jax.Array
    factors: tuple = dataclasses.field(metadata=dict(static=True))


@compilation.jit(static_argnames=("power", "progress"))
def _traced(a, power, progress=False):
    TRACES.append(power)
    if progress:
        jax.debug.callback(lambda v: None, a.x)
    return jnp.sum(a.x**power * jnp.asarray(a.factors))


def _stored(directory):
    return sorted(p.name for p in (directory / "executables").glob("*.executable"))


def test_executable_store_loads_programs_without_tracing_them(tmp_path, jax_cache_settings):
    """With the persistent cache on, a program of ``compilation.jit`` is stored as an executable
    and, once this process's programs are dropped (as a new process starts), loaded from the
    store without being traced again; another shape, static argument or static field of an
    argument is another program."""
    compilation.use_persistent_cache(tmp_path, min_compile_seconds=0)
    a = _Scaled(jnp.arange(1.0, 4.0), (1.0, 2.0, 3.0))
    TRACES.clear()
    assert float(_traced(a, 2)) == 36.0 and TRACES == [2]
    assert len(_stored(tmp_path)) == 1
    jax.clear_caches()
    compilation.clear_programs()
    assert float(_traced(a, 2)) == 36.0 and TRACES == [2]  # loaded, not traced
    assert float(_traced(_Scaled(a.x + 1.0, a.factors), 2)) == 70.0 and TRACES == [2]  # same program, other input
    assert float(_traced(a, 3)) == 98.0 and TRACES == [2, 3]
    assert float(_traced(_Scaled(a.x, (1.0, 2.0, 4.0)), 2)) == 45.0 and TRACES == [2, 3, 2]
    assert float(_traced(_Scaled(jnp.arange(1.0, 3.0), (1.0, 1.0)), 2)) == 5.0 and TRACES == [2, 3, 2, 2]
    assert len(_stored(tmp_path)) == 4
    abstract = _Scaled(jax.ShapeDtypeStruct((3,), jnp.float64), a.factors)  # as compile_solve passes a state
    program = _traced.compiled(abstract, 2)
    assert program.out_info.shape == () and TRACES == [2, 3, 2, 2]
    assert float(program(a, 2)) == 36.0


def test_executable_store_recompiles_what_it_cannot_load_or_store(tmp_path, jax_cache_settings):
    """An unreadable entry (here truncated) is compiled again and replaced; a program with a host
    callback, which cannot be serialised, runs without being stored."""
    compilation.use_persistent_cache(tmp_path, min_compile_seconds=0)
    a = _Scaled(jnp.arange(1.0, 4.0), (1.0, 1.0, 1.0))
    TRACES.clear()
    _traced(a, 1)
    (entry,) = (tmp_path / "executables").glob("*.executable")
    entry.write_bytes(entry.read_bytes()[:100])
    jax.clear_caches()
    compilation.clear_programs()
    assert float(_traced(a, 1)) == 6.0 and TRACES == [1, 1]
    jax.clear_caches()
    compilation.clear_programs()
    assert float(_traced(a, 1)) == 6.0 and TRACES == [1, 1]  # the replaced entry loads
    assert float(_traced(a, 1, progress=True)) == 6.0 and TRACES == [1, 1, 1]
    assert len(_stored(tmp_path)) == 1
