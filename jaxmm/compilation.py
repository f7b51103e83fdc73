"""``jit``: ``jax.jit`` with the XLA options jaxmm's programs compile with.

On CPUs, XLA (from jaxlib 0.10) hands element-wise and reduction fusions to YNNPACK; on the
kinematics of many knots at once (arrays of shape (knots, 37, 3, 3) on iRonCub) those run slower
than XLA's own loops, so jaxmm turns them off (docs/design-decisions.md, "YNNPACK fusions off").
XLA's tree reduction rewrite is off too: it doubles the kernels of every long reduction, which
the compile time follows (docs/design-decisions.md, "XLA's tree reduction rewrite off"). Each
option is passed only where this jaxlib knows it (checked once, by compiling a trivial
function); they change nothing on other backends.

``custom_calls`` and ``program_size`` read a program's size from its text (the compile benchmark,
and the test that each heavy kernel of the solver's iteration is compiled once).

``use_persistent_cache``: compiled programs kept on disk (JAX's persistent compilation cache), so
that a new process solving a problem structure solved before loads its programs instead of
compiling them again (the command line's default). Where JAX's cache is on, jaxmm's own programs
(``jit``) are also kept as executables under a key computed from their arguments' structure
without tracing them (``ExecutableStore``): JAX's cache key is a hash of the lowered program, so
each of its hits still traces and lowers the program (seconds for a solver iteration), which
this store skips.
"""

import collections
import contextlib
import dataclasses
import functools
import hashlib
import inspect
import os
import pathlib
import pickle
import re
import threading

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np
from jax.experimental import serialize_executable
from jax.experimental.compilation_cache import compilation_cache

_OPTIONS = {
    "xla_cpu_experimental_ynn_fusion_type": "",  # "": no YNNPACK fusions
    # Without XLA's tree reduction rewrite every reduction over more than 32 entries is one
    # kernel, not a reduce-window kernel feeding a reduce: 529 fewer kernels in the take-off's
    # iteration, its compile 9 % shorter, the same time per iteration (sums lose pairwise
    # summation's accuracy: at most n ε relative, n ≤ 10⁴ here).
    "xla_disable_hlo_passes": "tree_reduction_rewriter",
}


@functools.cache
def compiler_options():
    """The options jaxmm compiles with: those of ``_OPTIONS`` that this jaxlib knows (each tried
    once on a trivial function)."""
    known = {}
    for name, value in _OPTIONS.items():
        try:
            jax.jit(lambda x: x + 1, compiler_options={name: value}).lower(1.0).compile()
        except jax.errors.JaxRuntimeError:
            continue
        known[name] = value
    return known


class _Jitted:
    """A ``jax.jit`` of ``fn`` with ``compiler_options`` where it is compiled on its own, built
    at its first use (asking for the options compiles, so not at import); a plain one where it
    is traced inside another function (JAX takes options only from the outermost jit). Called
    on values while JAX's persistent cache is on, it runs the executable of ``compiled``."""

    def __init__(self, fn, kwargs):
        self._fn, self._kwargs = fn, kwargs
        self._nested = jax.jit(fn, **kwargs)
        static = kwargs.get("static_argnames", ())
        self._static = (static,) if isinstance(static, str) else tuple(static)
        self._signature = inspect.signature(fn)
        functools.update_wrapper(self, fn)

    @functools.cached_property
    def _jitted(self):
        return jax.jit(self._fn, compiler_options=compiler_options(), **self._kwargs)

    def __call__(self, *args, **kwargs):
        traced = any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((args, kwargs)))
        if traced:
            return self._nested(*args, **kwargs)
        if store() is None:
            return self._jitted(*args, **kwargs)
        return self.compiled(*args, **kwargs)(*args, **kwargs)

    def compiled(self, *args, **kwargs):
        """The ``Program`` compiled for arguments like these (values, or ``jax.ShapeDtypeStruct``
        leaves): from this process's memory, else from the ``ExecutableStore`` where JAX's
        persistent cache is on, else lowered and compiled (with JAX's cache off where the store
        is on, ``_compile_afresh``; through it otherwise) and kept in memory and in the store."""
        arguments, statics = self._split(args, kwargs)
        leaves, treedef = jax.tree.flatten(arguments)
        key = (self._fn, treedef, statics, tuple(_leaf_type(leaf) for leaf in leaves))
        if key not in _LOADED:
            _LOADED[key] = Program(self, _load_or_compile(self, arguments, statics, leaves, treedef))
        return _LOADED[key]

    def _split(self, args, kwargs):
        """({name: value} of the non-static arguments, defaults filled in; ((name, value), …) of
        the static ones)."""
        bound = self._signature.bind(*args, **kwargs)
        bound.apply_defaults()
        arguments = dict(bound.arguments)
        return arguments, tuple((name, arguments.pop(name)) for name in self._static)

    def __getattr__(self, name):  # lower, eval_shape, trace, …: those of the jax.jit
        if name.startswith("__") or name in ("_fn", "_kwargs"):
            raise AttributeError(name)
        return getattr(self._jitted, name)


class Program:
    """A compiled program of ``jit``: called with the function's arguments (static ones
    included, and ignored); ``out_info``: the ``jax.ShapeDtypeStruct`` tree of its result."""

    def __init__(self, jitted, executable):
        self._jitted, self._executable = jitted, executable

    @property
    def out_info(self):
        return jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype), self._executable.out_info)

    def __call__(self, *args, **kwargs):
        return self._executable(**self._jitted._split(args, kwargs)[0])


def _leaf_type(x):
    """(shape, dtype, weak type) of an argument's leaf: an array, a Python number or a
    ``jax.ShapeDtypeStruct``."""
    weak = x.weak_type if isinstance(x, jax.ShapeDtypeStruct) else jax.typeof(x).weak_type
    return np.shape(x), str(jnp.result_type(x)), bool(weak)


# The executables of ``_Jitted.compiled`` this process holds, by (function, argument structure,
# static arguments, argument types); ``clear_programs`` drops them.
_LOADED = {}


def loaded_programs():
    """How many compiled programs this process holds (``jit``'s executables; see ``clear_programs``)."""
    return len(_LOADED)


def clear_programs():
    """Drop the compiled programs this process holds (``jax.clear_caches`` for JAX's own): each
    holds thousands of memory mappings. Later calls load them again from the disk caches."""
    _LOADED.clear()


def _load_or_compile(jitted, arguments, statics, leaves, treedef):
    """The executable of ``jitted`` for these (non-static) ``arguments``, by keyword: loaded
    from the store where it has it, else compiled and stored."""
    place = store()
    key = None if place is None else place.key(jitted._fn, treedef, statics, leaves)
    executable = None if key is None else place.load(key)
    if executable is None:
        lowered = jitted._jitted.lower(**arguments, **dict(statics))
        if key is None:
            return lowered.compile()
        executable = _compile_afresh(lowered)
        place.save(key, executable)
    return executable


def _compile_afresh(lowered):
    """``lowered.compile()`` with JAX's persistent cache off: an executable loaded from that
    cache serialises without its kernels (XLA's CPU backend) and fails when run after being
    loaded from the store; the store keeps these programs instead."""
    with _persistent_cache_off():
        return lowered.compile()


# Compiles in flight in ``_persistent_cache_off`` (threads may compile several programs at once,
# ``programs.compiled_programs``), and JAX's setting before the first of them.
_CACHE_OFF = {"count": 0, "enabled": None}
_CACHE_OFF_LOCK = threading.Lock()


@contextlib.contextmanager
def _persistent_cache_off():
    """JAX's persistent cache off from the first compile that asks for it until the last one
    ends, whatever the threads doing them (JAX's setting is global)."""
    with _CACHE_OFF_LOCK:
        if _CACHE_OFF["count"] == 0:
            _CACHE_OFF["enabled"] = jax.config.jax_enable_compilation_cache
            jax.config.update("jax_enable_compilation_cache", False)
            compilation_cache.reset_cache()  # JAX decides once whether its cache is used
        _CACHE_OFF["count"] += 1
    try:
        yield
    finally:
        with _CACHE_OFF_LOCK:
            _CACHE_OFF["count"] -= 1
            if _CACHE_OFF["count"] == 0:
                jax.config.update("jax_enable_compilation_cache", _CACHE_OFF["enabled"])
                compilation_cache.reset_cache()


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

    jaxmm's own programs (``jit``: a solve's start, advance and finish) are kept apart, in
    ``directory/executables`` (``ExecutableStore``), and loaded without being traced; the size
    limit does not apply to them (one take-off N = 70 iteration program: ≈ 14 MB).
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


class ExecutableStore:
    """Compiled executables on disk, one file ``<key>.executable`` each in ``directory``, keyed
    without tracing: by the function (module, name) and the source of the ``jaxmm`` package, the
    structure of the arguments (pytree nodes and their static data), their shapes and dtypes,
    the static arguments, and everything else a program depends on (JAX and jaxlib versions,
    backend and devices, ``XLA_FLAGS``, jaxmm's compiler options, 64-bit mode). A key that
    cannot be computed reliably (a static value whose text depends on the process, such as a
    function's address) simply never hits. An entry that cannot be read is compiled again and
    overwritten. Only trusted users should be able to write to ``directory``: JAX runs what it
    loads."""

    def __init__(self, directory):
        self.directory = pathlib.Path(directory)

    def key(self, fn, treedef, statics, leaves):
        """The hex key of ``fn`` for arguments of structure ``treedef`` with these static
        (name, value) pairs and array ``leaves``."""
        digest = hashlib.sha256()
        for part in (_environment(), fn.__module__, fn.__qualname__, _canonical(treedef), repr(statics),
                     [_leaf_type(x) for x in leaves]):
            digest.update(repr(part).encode())
            digest.update(b"\0")
        return digest.hexdigest()

    def load(self, key):
        """The executable stored under ``key``, or None (absent, or unreadable)."""
        path = self.directory / f"{key}.executable"
        try:
            payload, in_tree, out_tree = pickle.loads(path.read_bytes())
            _initialise_custom_calls()
            return serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
        except Exception:  # absent, half-written by another process, or from another build
            return None

    def save(self, key, executable):
        """Store ``executable`` under ``key`` (atomically: written aside, then renamed); one
        that cannot be serialised (a host callback in it) is left out."""
        try:
            blob = pickle.dumps(serialize_executable.serialize(executable))
        except Exception:  # host callbacks (progress printing) are not serialisable
            return
        self.directory.mkdir(parents=True, exist_ok=True)
        aside = self.directory / f"{key}.{os.getpid()}.partial"
        aside.write_bytes(blob)
        os.replace(aside, self.directory / f"{key}.executable")


def store():
    """The ``ExecutableStore`` in use: ``executables/`` inside JAX's persistent cache directory
    while that cache is on (``use_persistent_cache``, ``$JAX_COMPILATION_CACHE_DIR``), else None."""
    directory = jax.config.jax_compilation_cache_dir
    return ExecutableStore(pathlib.Path(directory) / "executables") if directory else None


@functools.cache
def _environment():
    """Everything besides the arguments that a compiled program of jaxmm depends on."""
    package = pathlib.Path(__file__).resolve().parent
    source = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        source.update(str(path.relative_to(package)).encode() + b"\0" + path.read_bytes())
    devices = [(d.platform, d.device_kind) for d in jax.devices()]
    return (source.hexdigest(), jax.__version__, jaxlib.__version__,
            jax.default_backend(), devices, os.environ.get("XLA_FLAGS", ""), sorted(compiler_options().items()),
            bool(jax.config.jax_enable_x64), str(jax.config.jax_default_matmul_precision))


@functools.cache
def _initialise_custom_calls():
    """Lower one Cholesky factorisation: JAX registers its LAPACK kernels when it first lowers
    one, and a loaded executable that calls them before that crashes the process."""
    jax.jit(jnp.linalg.cholesky).lower(np.eye(1))


def _canonical(value):
    """A text of ``value`` (a pytree structure, its static data) that differs wherever the
    value does: arrays by their bytes, containers item by item, other objects by ``repr``."""
    if isinstance(value, jax.tree_util.PyTreeDef):
        node, data = value.node_data() or (None, None)
        return (f"{getattr(node, '__module__', '')}.{getattr(node, '__qualname__', repr(node))}", _canonical(data),
                tuple(_canonical(child) for child in value.children()))
    if isinstance(value, np.ndarray):
        digest = hashlib.sha256(np.ascontiguousarray(value).tobytes()).hexdigest()
        return ("array", value.dtype.str, value.shape, digest)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return (f"{type(value).__module__}.{type(value).__qualname__}",
                tuple((f.name, _canonical(getattr(value, f.name))) for f in dataclasses.fields(value)))
    if isinstance(value, (tuple, list)):
        return (type(value).__name__, tuple(_canonical(v) for v in value))
    if isinstance(value, dict):
        return ("dict", tuple((repr(k), _canonical(v)) for k, v in value.items()))
    if isinstance(value, frozenset):
        return ("frozenset", tuple(sorted(repr(_canonical(v)) for v in value)))
    return repr(value)


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


def _instructions(compiled_text):
    """(instruction line, runs as a kernel of its own) for every instruction of an optimised HLO
    text: kernels are those outside fusion bodies, parameters, constants, tuples and bitcasts
    left out."""
    fused = False
    for line in compiled_text.splitlines():
        header = re.match(r"\s*(?:ENTRY )?%?([\w.\-]+) .*\{\s*$", line)
        if header and "=" not in line.split("{")[0]:
            fused = header.group(1).startswith("fused_") or ".fused" in header.group(1)
            continue
        op = re.match(r"\s*(?:ROOT )?%?[\w.\-]+ = (?:\([^=]*?\)|\S+) ([\w\-]+)\(", line)
        if op:
            yield line, (not fused) and op.group(1) not in _TRIVIAL


def program_size(compiled_text):
    """(HLO instructions, kernels) of a compiled program's optimised HLO text
    (``….compile().as_text()``): every instruction, and those outside fusion bodies that run
    as an operation of their own (fusions, custom calls, dots, copies, loops and their
    parts; parameters, constants, tuples and bitcasts left out)."""
    instructions = kernels = 0
    for _, kernel in _instructions(compiled_text):
        instructions += 1
        kernels += kernel
    return instructions, kernels


def _source_files(compiled_text):
    """{stack frame id: the source file of its innermost location} from an HLO text's
    ``FileNames``, ``FileLocations`` and ``StackFrames`` tables."""
    tables, section = {"FileNames": {}, "FileLocations": {}, "StackFrames": {}}, None
    for line in compiled_text.splitlines():
        if line in tables:
            section = line
        elif section and not line.strip():
            section = None
        elif section:
            key, value = line.split(" ", 1)
            tables[section][int(key)] = value
    files = {k: v.strip('"') for k, v in tables["FileNames"].items()}
    location_file = {k: int(re.search(r"file_name_id=(\d+)", v).group(1)) for k, v in tables["FileLocations"].items()}
    return {k: files[location_file[int(re.search(r"file_location_id=(\d+)", v).group(1))]]
            for k, v in tables["StackFrames"].items()}


def kernel_sources(compiled_text):
    """{source module: kernels} of a compiled program's optimised HLO text: each kernel
    (``program_size``'s) under the file of the innermost source line in its metadata, named from
    the package directory on (``jaxmm/solver/trees.py``; another file by its base name), or
    ``"(no source)"`` (loop plumbing, copies and layout changes XLA adds)."""
    frames = _source_files(compiled_text)
    counts = collections.Counter()
    for line, kernel in _instructions(compiled_text):
        if kernel:
            counts[_source_of(line, frames)] += 1
    return dict(counts)


def _source_of(line, frames):
    """The source module (``_module_name``) of an HLO instruction line, from its stack frame
    and the program's ``_source_files`` table ``frames``."""
    frame = re.search(r"stack_frame_id=(\d+)", line)
    return _module_name(frames.get(int(frame.group(1))) if frame else None)


# The environment under which XLA's CPU compiler logs the time of each kernel's MLIR emission and
# LLVM compilation (read by ``codegen_seconds``); it must be set before jaxlib is loaded.
CODEGEN_TIMERS = {"TF_CPP_MIN_LOG_LEVEL": "0", "TF_CPP_VMODULE": "fusion_compiler=1,ir_compiler=1"}
_TIMER = re.compile(r"Compiled (?:MLIR|LLVM) module: (\S+) time: ([\d.]+) (s|ms|us)\b")
_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6}


def codegen_seconds(log_text, compiled_text):
    """{source module: seconds} of XLA's code generation for a compiled program: the per-kernel
    timers its CPU compiler logs under ``CODEGEN_TIMERS`` (``log_text``), each kernel named
    after the HLO instruction it compiles, attributed as ``kernel_sources`` attributes kernels
    (the innermost source line of that instruction in ``compiled_text``). A module the program
    does not name counts under "(unattributed)": a kernel of another program compiled in the
    same process, or the shared modules ("…_part_00") into which XLA compiles kernels when its
    fusion emitters are off (``xla_cpu_use_fusion_emitters=false``; by default they are on).
    Kernel counts mislead here: XLA reuses one compiled kernel for identical fusions (not for
    identical dots), a buffer copy costs nothing, and every generated kernel costs ≈ 20 ms
    however small."""
    frames = _source_files(compiled_text)
    where = {re.match(r"\s*(?:ROOT )?%?([\w.\-]+) = ", line).group(1): _source_of(line, frames)
             for line, _ in _instructions(compiled_text)}
    seconds = collections.Counter()
    for match in _TIMER.finditer(log_text):
        name = re.sub(r"^(?:__compute_module_)+|(?:_elemental)?_kernel_module$", "", match.group(1))
        seconds[where.get(name, "(unattributed)")] += float(match.group(2)) * _UNITS[match.group(3)]
    return dict(seconds)


def _module_name(path):
    """``jaxmm/…`` for a file of the package, the base name for another, "(no source)" for None."""
    if path is None:
        return "(no source)"
    return "jaxmm/" + path.rsplit("/jaxmm/", 1)[1] if "/jaxmm/" in path else os.path.basename(path)
