"""The solver's iteration program holds each heavy kernel once: the block factorisation and the
block solve appear at one call site per iteration (in the normal step, the second-order
corrections, soft restoration, the restoration phase and iterative refinement alike), and so
the Cholesky factorisations and triangular solves that XLA compiles (every call inlined) are
exactly those of one ``linalg.factor`` and one ``linalg.solve``. A change that inlines a second
copy of either makes these counts grow."""

import dataclasses
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmm  # noqa: F401  (float64)
from jaxmm import compilation
from jaxmm.rigid_body import so3
from jaxmm.solver import interior_point as ip
from jaxmm.solver import linalg
from test_solver import CAPPED, K, integrator

CHOLESKY, TRIANGULAR = "lapack_dpotrf_ffi", "lapack_dtrsm_ffi"


def lapack_calls(fn, *args, **static):
    return compilation.custom_calls(jax.jit(fn, static_argnames=tuple(static)).lower(*args, **static).as_text())


def one_factor_and_one_solve(n, ng):
    """The LAPACK calls of one ``linalg.factor`` and one ``linalg.solve`` of K blocks of n with
    ng globals."""
    D, L = jnp.eye(n)[None].repeat(K, 0), jnp.zeros((K - 1, n, n))
    B, C = jnp.zeros((K, n, ng)), jnp.eye(ng)
    factor = lapack_calls(linalg.factor, D, L, B, C)
    chol = linalg.factor(D, L, B, C)
    solve = lapack_calls(linalg.solve, chol, jnp.zeros((K, n)), jnp.zeros(ng))
    return {name: factor.get(name, 0) + solve.get(name, 0) for name in (CHOLESKY, TRIANGULAR)}


@pytest.mark.parametrize("restoration", [True, False], ids=["with restoration phase", "without"])
def test_the_iteration_factors_and_solves_at_one_call_site_each(restoration):
    nlp = integrator(CAPPED, energy_cap=0.01)
    options = dataclasses.replace(ip.Options(), max_restoration_iterations=100 if restoration else 0)
    state = ip.start(nlp, jnp.zeros((K, 3)), jnp.zeros(1), options)
    calls = lapack_calls(lambda nlp, state: ip.advance(nlp, state, options, 3), nlp, state)
    expected = one_factor_and_one_solve(3, 1)
    assert expected[CHOLESKY] > 0 and expected[TRIANGULAR] > 0
    assert {name: calls.get(name, 0) for name in expected} == expected


def test_the_counter_sees_every_copy_of_an_inlined_call():
    """Two calls of the same jitted function count twice, as XLA compiles them."""
    factor = jax.jit(jnp.linalg.cholesky)
    A = jnp.eye(3)
    once = compilation.custom_calls(jax.jit(lambda a: factor(a)).lower(A).as_text())
    twice = compilation.custom_calls(jax.jit(lambda a: factor(a) + factor(2 * a)).lower(A).as_text())
    assert twice[CHOLESKY] == 2 * once[CHOLESKY] == 2


def test_the_program_size_counts_instructions_and_kernels():
    instructions, kernels = compilation.program_size(jax.jit(lambda x: jnp.sin(x) @ x).lower(jnp.eye(3)).compile().as_text())
    assert instructions >= kernels >= 1
    bigger = compilation.program_size(jax.jit(lambda x: jnp.linalg.cholesky(jnp.sin(x) @ x.T + 3 * jnp.eye(3)))
                                      .lower(jnp.eye(3)).compile().as_text())
    assert bigger[0] > instructions and np.isfinite(bigger[1])


def test_the_kernels_are_attributed_to_their_source_files():
    """Every kernel is counted once, under the module whose line made it: a jitted quaternion
    exponential's kernels come from ``jaxmm/rigid_body/so3.py``."""
    text = jax.jit(jax.vmap(so3.quaternion_exp)).lower(jnp.ones((4, 3))).compile().as_text()
    sources = compilation.kernel_sources(text)
    assert sum(sources.values()) == compilation.program_size(text)[1]
    assert sources.get("jaxmm/rigid_body/so3.py", 0) >= 1


def test_code_generation_seconds_are_attributed_to_their_source_files(tmp_path):
    """XLA's per-kernel timers, logged by a fresh process under ``CODEGEN_TIMERS`` while it
    compiles a vmapped quaternion exponential with XLA's default flags (fusion emitters on: one
    module per kernel), add up to seconds under ``so3.py``; a timer of a module the program
    does not name counts under "(unattributed)"."""
    script = ("import sys, jax, jax.numpy as jnp, jaxmm; from jaxmm.rigid_body import so3; "
              "text = jax.jit(jax.vmap(so3.quaternion_exp)).lower(jnp.ones((4, 3))).compile().as_text(); "
              "open(sys.argv[1], 'w').write(text)")
    compiled = tmp_path / "compiled.txt"
    environment = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR", "XLA_FLAGS")}
    result = subprocess.run([sys.executable, "-c", script, str(compiled)], capture_output=True, text=True,
                            env=dict(environment, **compilation.CODEGEN_TIMERS))
    assert result.returncode == 0, result.stderr[-2000:]
    log = result.stderr + "Compiled LLVM module: __compute_module_not_in_this_program_kernel_module time: 2.5 ms\n"
    seconds = compilation.codegen_seconds(log, compiled.read_text())
    assert seconds.get("jaxmm/rigid_body/so3.py", 0.0) > 0.0
    assert seconds["(unattributed)"] >= 2.5e-3 and all(v >= 0.0 for v in seconds.values())
