"""``tools/profile_iteration.py``'s attribution of profiled XLA operations to jaxmm
functions, on a small program whose operations come from known functions."""

import importlib.util
import pathlib
import sys
import tempfile

import jax
import jax.numpy as jnp
import numpy as np

from jaxmm.rigid_body import so3

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # profile_iteration.py imports benchmarks/machine.py
spec = importlib.util.spec_from_file_location("profile_iteration", ROOT / "tools" / "profile_iteration.py")
profile_iteration = importlib.util.module_from_spec(spec)
spec.loader.exec_module(profile_iteration)


def _program(quaternions, matrices):
    rotations = jax.vmap(so3.quaternion_to_rotation)(quaternions)
    return jnp.einsum("kij,kjl->kil", rotations, matrices).sum() + jnp.linalg.cholesky(matrices).sum()


def test_operations_are_attributed_to_the_jaxmm_functions_that_emitted_them():
    rng = np.random.default_rng(0)
    quaternions = rng.normal(size=(64, 4))
    X = rng.normal(size=(64, 3, 3))
    matrices = X @ np.swapaxes(X, 1, 2) + 3 * np.eye(3)
    compiled = jax.jit(_program).lower(quaternions, matrices).compile()
    origins = profile_iteration.stack_tables(compiled.as_text())
    frames = {name: profile_iteration.jaxmm_frames(stack) for name, stack in origins.items()}
    # Some operations come from so3.quaternion_to_rotation, and their stacks reach it through
    # this test's _program (which is not in jaxmm, so it is not among the jaxmm frames).
    assert any(("rigid_body/so3.py", "quaternion_to_rotation") in f for f in frames.values())
    assert not any(any(module.startswith("tests") for module, _ in f) for f in frames.values())
    jax.block_until_ready(compiled(quaternions, matrices))
    with tempfile.TemporaryDirectory() as directory:
        jax.profiler.start_trace(directory)
        for _ in range(3):
            jax.block_until_ready(compiled(quaternions, matrices))
        jax.profiler.stop_trace()
        times, counts, span, inside = profile_iteration.operation_times(directory)
    assert times and 0 < inside <= span
    assert not any(name.startswith(profile_iteration.CONTAINERS) for name in times)
    assert all(counts[name] == 3 for name in times)  # each operation once per call
    rotation = [name for name in times if ("rigid_body/so3.py", "quaternion_to_rotation") in frames.get(name, ())]
    assert rotation and all(times[name] > 0 for name in rotation)
    assert any("cholesky" in name and not frames.get(name) for name in times)  # called here, not in jaxmm


def test_every_instruction_has_its_shape_and_opcode():
    """The unattributed operations are listed by what they are: each instruction of the compiled
    text with its result shape and opcode (the Cholesky's input is f64[64,3,3])."""
    matrices = np.broadcast_to(2 * np.eye(3), (64, 3, 3))
    compiled = jax.jit(lambda m: jnp.linalg.cholesky(m) * 2.0).lower(matrices).compile()
    text = compiled.as_text()
    signatures = profile_iteration.instruction_signatures(text)
    defined = {line.split("=")[0].strip().removeprefix("ROOT ").lstrip("%") for line in text.splitlines()
               if line.strip().startswith(("%", "ROOT %")) and " = " in line}
    assert signatures and set(signatures) <= defined
    assert all(what.split(" ")[-1].replace("-", "_").isidentifier() for what in signatures.values())
    assert any(what.startswith("f64[64,3,3]") for what in signatures.values())


def test_an_unknown_option_is_refused_before_compiling():
    """``--option`` reads solver options as ``tools/rounding.py`` does; a name that is not one
    stops the script with a usage error naming the known ones, before any compilation."""
    import subprocess

    run = subprocess.run([sys.executable, str(ROOT / "tools" / "profile_iteration.py"), "--option", "no_such=1"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 2
    assert "no_such" in run.stderr and "regularisation_decrease" in run.stderr and "compiling" not in run.stderr
