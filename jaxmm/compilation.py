"""``jit``: ``jax.jit`` with the XLA options jaxmm's programs compile with.

On CPUs, XLA (measured with jaxlib 0.10.2) hands element-wise and reduction fusions to
YNNPACK; on the kinematics of many knots at once (arrays of shape (knots, 37, 3, 3) on iRonCub)
those ran slower than XLA's own loops. Without them, one core of this project's machine: the
kinematics Jacobian of 71 knots 30 → 22 ms, its second derivative 55 → 44 ms (200 knots:
88 → 63 and 168 → 118 ms); the first 30 take-off iterations at N = 70 0.502 → 0.427 s each
(same run); at N = 14 no difference beyond the machine's noise (±15 %). The option is passed
only where this jaxlib knows it (checked once, by compiling a trivial function); it changes
nothing on other backends.
"""

import functools

import jax

_OPTIONS = {"xla_cpu_experimental_ynn_fusion_type": ""}  # "": no YNNPACK fusions


@functools.cache
def compiler_options():
    """The options jaxmm compiles with: {} where this jaxlib does not know them."""
    try:
        jax.jit(lambda x: x + 1, compiler_options=_OPTIONS).lower(1.0).compile()
    except jax.errors.JaxRuntimeError:
        return {}
    return dict(_OPTIONS)


class _Jitted:
    """A ``jax.jit`` of ``fn`` with ``compiler_options`` where it is compiled on its own, built
    at its first use (asking for the options compiles, so not at import); a plain one where it
    is traced inside another function (JAX takes options only from the outermost jit)."""

    def __init__(self, fn, kwargs):
        self._fn, self._kwargs = fn, kwargs
        self._nested = jax.jit(fn, **kwargs)
        functools.update_wrapper(self, fn)

    @functools.cached_property
    def _jitted(self):
        return jax.jit(self._fn, compiler_options=compiler_options(), **self._kwargs)

    def __call__(self, *args, **kwargs):
        traced = any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((args, kwargs)))
        return (self._nested if traced else self._jitted)(*args, **kwargs)

    def __getattr__(self, name):  # lower, eval_shape, trace, …: those of the jax.jit
        if name.startswith("__") or name in ("_fn", "_kwargs"):
            raise AttributeError(name)
        return getattr(self._jitted, name)


def jit(fn=None, **kwargs):
    """``jax.jit(fn, **kwargs)`` compiled with ``compiler_options()``; usable as a decorator,
    with or without keyword arguments (``static_argnames`` …)."""
    if fn is None:
        return functools.partial(jit, **kwargs)
    return _Jitted(fn, kwargs)
