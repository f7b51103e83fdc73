"""``jit``: ``jax.jit`` with the XLA options jaxmm's programs compile with.

On CPUs, XLA (from jaxlib 0.10) hands element-wise and reduction fusions to YNNPACK; on the
kinematics of many knots at once (arrays of shape (knots, 37, 3, 3) on iRonCub) those run slower
than XLA's own loops, so jaxmm turns them off (docs/design-decisions.md, "YNNPACK fusions off").
The option is passed only where this jaxlib knows it (checked once, by compiling a trivial
function); it changes nothing on other backends.

``custom_calls`` and ``program_size`` read a program's size from its text (the compile benchmark,
and the test that each heavy kernel of the solver's iteration is compiled once).

``use_persistent_cache``: compiled programs kept on disk (JAX's persistent compilation cache), so
that a new process solving a problem structure solved before loads its programs instead of
compiling them again (the command line's default).
"""

import collections
import functools
import os
import pathlib
import re

import jax
from jax.experimental.compilation_cache import compilation_cache

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


def default_cache_directory():
    """Where ``use_persistent_cache`` keeps programs by default: ``$JAXMM_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/jaxmm/xla``, else ``~/.cache/jaxmm/xla``."""
    if os.environ.get("JAXMM_CACHE_DIR"):
        return pathlib.Path(os.environ["JAXMM_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache"
    return pathlib.Path(base) / "jaxmm" / "xla"


def use_persistent_cache(directory=None, max_size=None, min_compile_seconds=1.0):
    """Keep every compiled program that took at least ``min_compile_seconds`` [s] to compile in
    ``directory`` (default: ``default_cache_directory()``), and load it from there in later
    processes: a problem structure (robot, knot count, options) is compiled once per machine
    and JAX/jaxlib version. Returns the directory (created if missing).

    max_size [bytes]: the cache's limit, least recently used entries going first (default: JAX's
    ``$JAX_COMPILATION_CACHE_MAX_SIZE`` when set, else 16 GiB). A limit also turns on JAX's file
    lock, without which one process can read a program another is still writing. Only trusted
    users should be able to write to the directory: JAX runs what it loads. Takes effect for
    programs compiled after the call (programs already in this process's memory are reused as
    they are).
    """
    path = pathlib.Path(default_cache_directory() if directory is None else directory).expanduser()
    if path.exists() and not path.is_dir():
        raise NotADirectoryError(f"compilation cache directory {path} exists and is not a directory")
    if max_size is None:
        max_size = jax.config.jax_compilation_cache_max_size
        max_size = max_size if max_size > 0 else 16 << 30
    if not int(max_size) > 0:
        raise ValueError(f"max_size must be a positive number of bytes, got {max_size}")
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_max_size", int(max_size))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_seconds))
    if jax.config.jax_compilation_cache_dir != str(path):
        jax.config.update("jax_compilation_cache_dir", str(path))
        compilation_cache.reset_cache()  # JAX opens its cache once; reopen it at the new place
    return path


def custom_calls(lowered_text):
    """{target: count} of the custom calls (LAPACK's ``lapack_dpotrf_ffi`` Cholesky, its
    ``lapack_dtrsm_ffi`` triangular solves, …) in a lowered program's StableHLO text
    (``jax.jit(f).lower(...).as_text()``), every call of a function counted with the calls
    inside it: the number of copies XLA compiles, which inlines every call."""
    bodies, current = {}, None
    for line in lowered_text.splitlines():
        found = re.match(r"\s*func\.func (?:public |private )?@([\w.$-]+)", line)
        if found:
            current = found.group(1)
            bodies[current] = []
        elif current is not None:
            bodies[current].append(line)

    @functools.cache
    def count(function):
        total = collections.Counter()
        for line in bodies[function]:
            total.update(re.findall(r"custom_call @(\w+)", line))
            for callee in re.findall(r"(?<!custom_)call @([\w.$-]+)", line):
                if callee in bodies:
                    total += count(callee)
        return total

    return dict(count("main")) if "main" in bodies else {}


_TRIVIAL = {"parameter", "constant", "get-tuple-element", "tuple", "bitcast"}


def program_size(compiled_text):
    """(HLO instructions, kernels) of a compiled program's optimised HLO text
    (``….compile().as_text()``): every instruction, and those outside fusion bodies that run
    as an operation of their own (fusions, custom calls, dots, copies, loops and their
    parts; parameters, constants, tuples and bitcasts left out)."""
    instructions = kernels = 0
    fused = False
    for line in compiled_text.splitlines():
        header = re.match(r"\s*(?:ENTRY )?%?([\w.\-]+) .*\{\s*$", line)
        if header and "=" not in line.split("{")[0]:
            fused = header.group(1).startswith("fused_") or ".fused" in header.group(1)
            continue
        op = re.match(r"\s*(?:ROOT )?%?[\w.\-]+ = (?:\([^=]*?\)|\S+) ([\w\-]+)\(", line)
        if op:
            instructions += 1
            kernels += (not fused) and op.group(1) not in _TRIVIAL
    return instructions, kernels
