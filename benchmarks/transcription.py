"""Time the take-off NLP's residuals and derivatives: the JAX stage-wise transcription against
the CasADi reference (``jaxmm.reference``), both at the published initial guess.

Both sides get the same problem: ``tasks.scenario("take_off", knots=N)`` on the default
assembled iRonCub (the reference reads the same robot from ``jaxmm.assemble_urdf``, written to
a temporary file), over the same scaled decision vector (z̃ = z / d per knot, then T_total).

What is measured (wall clock; run time = median over --repeats calls after one untimed warm-up
call; compile and build times separately):

* JAX (``jaxmm.stagewise``), each ``jax.jit``-compiled with
  ``jax.jit(f).lower(...).compile()`` (tracing, lowering and XLA compilation):
  - residuals: every constraint function and the cost (``stagewise.residuals``);
  - constraint Jacobian blocks: ``jax.jacfwd`` of the four constraint functions vmapped over
    the knots, exactly as ``stagewise.blocks`` does;
  - cost Hessian blocks: the knot costs' Hessians vmapped over the knots, as ``stagewise.blocks``;
  - all blocks: ``stagewise.blocks`` (the two above and the cost gradient).
* CasADi (``ReferenceNLP.symbolic``, ADAM kinematics, the MX expressions its IPOPT solve uses),
  one ``casadi.Function`` per row; build time = the Function's construction, symbolic
  differentiation included (the ``ReferenceNLP`` construction itself is printed apart):
  - g and f: every constraint, stacked as for IPOPT, and the cost;
  - jac_g: the sparse constraint Jacobian;
  - hess_f: the cost Hessian;
  - jac_g, grad_f and hess_f in one Function: the counterpart of ``stagewise.blocks``;
  - hess_l: the upper triangle of the Hessian of the Lagrangian f + λᵀg (IPOPT's exact
    Hessian, random λ), which has no JAX counterpart.

The run asserts that both sides agree, per constraint family, on the constraint values, on the
Jacobian times a random vector, and on the cost and its Hessian times that vector.

Usage: python benchmarks/transcription.py [--knots 70] [--repeats 7]
"""

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"  # before numpy is imported

import argparse  # noqa: E402
import logging  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import casadi as cs  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxmm  # noqa: E402  (enables float64)
from machine import format_time, log, machine_lines  # noqa: E402
from jaxmm import tasks  # noqa: E402
from jaxmm.reference import ReferenceNLP  # noqa: E402
from jaxmm.transcription import nlp as transcription  # noqa: E402
from jaxmm import stagewise  # noqa: E402

SEED = 0
TOLERANCE = 1e-9  # on |JAX − CasADi| / max(1, max |CasADi|)
PAPER_JACOBIAN = 66e-3  # s per constraint-Jacobian evaluation of the paper's code at N = 70
GOAL_JACOBIAN = 5e-3


def median_seconds(run, repeats):
    """Median wall time of run() over repeats calls, after one untimed warm-up call."""
    run()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


# ------------------------------------------------------------------------------------------ JAX


def constraint_jacobians(nlp, Z, theta):
    """The constraint blocks of ``stagewise.blocks`` only: for each of path equality, transition
    equality, path inequality, transition inequality, (∂/∂z_k, [∂/∂z_{k+1},] ∂/∂θ)."""
    f, a = nlp.functions, nlp.args

    def path(fn):
        return jax.vmap(jax.jacfwd(fn, argnums=(1, 2)), in_axes=(None, 0, None))(a, Z, theta)

    def transition(fn):
        return jax.vmap(jax.jacfwd(fn, argnums=(1, 2, 3)), in_axes=(None, 0, 0, None))(a, Z[:-1], Z[1:], theta)

    return (
        path(f.path_equality),
        transition(f.transition_equality),
        path(f.path_inequality),
        transition(f.transition_inequality),
    )


def cost_hessian(nlp, Z, theta):
    """The cost Hessian blocks of ``stagewise.blocks`` only: (zz (K, nz, nz), zθ (K, nz, ng), θθ)."""
    f, a = nlp.functions, nlp.args
    knot_grad = jax.grad(f.knot_cost, argnums=(1, 2))
    hessian = jax.vmap(jax.jacfwd(knot_grad, argnums=(1, 2)), in_axes=(None, 0, None, 0))(a, Z, theta, nlp.knot_data)
    (zz, ztheta), (_, thetatheta) = hessian
    return zz, ztheta, jnp.sum(thetatheta, axis=0) + jax.hessian(f.global_cost, argnums=1)(a, theta)


JAX_FUNCTIONS = {
    "residuals": stagewise.residuals,
    "constraint Jacobian": constraint_jacobians,
    "cost Hessian": cost_hessian,
    "all blocks": stagewise.blocks,
}


def time_jax(nlp, Z, theta, repeats):
    """{name: (compile seconds, run seconds, outputs)} for every function of JAX_FUNCTIONS."""
    results = {}
    for name, function in JAX_FUNCTIONS.items():
        log(f"JAX {name}: compiling...")
        start = time.perf_counter()
        compiled = jax.jit(function).lower(nlp, Z, theta).compile()
        compile_time = time.perf_counter() - start
        run = median_seconds(lambda: jax.block_until_ready(compiled(nlp, Z, theta)), repeats)
        results[name] = (compile_time, run, compiled(nlp, Z, theta))
    return results


# --------------------------------------------------------------------------------------- CasADi


def casadi_expressions(reference):
    """The scaled decision vector w̃ (MX), the multipliers λ (MX), g(w̃) stacked as for IPOPT
    (families in ``family_names`` order, each knot-major), and f(w̃)."""
    w = cs.MX.sym("w", reference.n_variables)
    families, costs = reference.symbolic(cs.DM(reference.scale()) * w)
    g = cs.vertcat(*[cs.vec(families[name]) for name in reference.family_names()])
    return w, cs.MX.sym("lam", g.shape[0]), g, costs["total"]


def casadi_builders(w, lam, g, f):
    """{name: (builder of the Function, its inputs: "w" or "w, λ")}."""

    def blocks():
        hess_f, grad_f = cs.hessian(f, w)
        return cs.Function("blocks", [w], [cs.jacobian(g, w), grad_f, hess_f])

    def hess_l():
        return cs.Function("hess_l", [w, lam], [cs.triu(cs.hessian(f + cs.dot(lam, g), w)[0])])

    return {
        "g and f": lambda: cs.Function("g_f", [w], [g, f]),
        "jac_g": lambda: cs.Function("jac_g", [w], [cs.jacobian(g, w)]),
        "hess_f": lambda: cs.Function("hess_f", [w], [cs.hessian(f, w)[0]]),
        "jac_g, grad_f, hess_f": blocks,
        "hess_l": hess_l,
    }


def time_casadi(expressions, w0, multipliers, repeats):
    """{name: (build seconds, run seconds, outputs)} for every Function of casadi_builders."""
    results = {}
    for name, build in casadi_builders(*expressions).items():
        log(f"CasADi {name}: building...")
        start = time.perf_counter()
        function = build()
        build_time = time.perf_counter() - start
        inputs = (w0,) if function.n_in() == 1 else (w0, multipliers)
        run = median_seconds(lambda: function(*inputs), repeats)
        results[name] = (build_time, run, function(*inputs))
    return results


# --------------------------------------------------------------------------------------- checks


def split_stacked(task, reference, vector):
    """A stacked constraint vector (CasADi's g order) → {family: (K, rows)}."""
    rows = {name: size for families in transcription.family_rows(task).values() for name, size in families}
    out, start = {}, 0
    for name in reference.family_names():
        size = reference.n_stages(name) * rows[name]
        out[name] = np.asarray(vector).ravel()[start : start + size].reshape(-1, rows[name])
        start += size
    return out


def jacobian_times(jacobians, V, v_theta):
    """The JAX constraint blocks times a direction (V (K, nz), v_θ): a ``Residuals`` (cost 0)."""
    path_eq, transition_eq, path_in, transition_in = jacobians

    def path(blocks):
        z, theta = blocks
        return jnp.einsum("kmn,kn->km", z, V) + theta @ v_theta

    def transition(blocks):
        z, z_next, theta = blocks
        return jnp.einsum("kmn,kn->km", z, V[:-1]) + jnp.einsum("kmn,kn->km", z_next, V[1:]) + theta @ v_theta

    return stagewise.Residuals(
        cost=jnp.zeros(()),
        path_equality=path(path_eq),
        transition_equality=transition(transition_eq),
        path_inequality=path(path_in),
        transition_inequality=transition(transition_in),
    )


def cost_hessian_times(hessian, V, v_theta):
    """The JAX cost Hessian blocks times a direction, flattened like w̃."""
    zz, ztheta, thetatheta = hessian
    knots = jnp.einsum("kmn,kn->km", zz, V) + ztheta @ v_theta
    theta = jnp.einsum("kni,kn->i", ztheta, V) + thetatheta @ v_theta
    return np.concatenate([np.ravel(knots), np.asarray(theta)])


def relative_difference(ours, reference):
    ours, reference = np.asarray(ours), np.asarray(reference)
    assert ours.shape == reference.shape, (ours.shape, reference.shape)
    return float(np.abs(ours - reference).max(initial=0.0) / max(1.0, np.abs(reference).max(initial=0.0)))


def agreement(task, reference, jax_results, casadi_results, direction):
    """Worst relative difference of the constraint values (per family), of the Jacobian times
    the direction (per family), of the cost and of the cost Hessian times the direction."""
    V, v_theta = direction
    v = np.concatenate([np.ravel(V), np.asarray(v_theta)])
    g, f = casadi_results["g and f"][2]
    jac_g = casadi_results["jac_g"][2]
    hess_f = casadi_results["hess_f"][2]
    residuals = jax_results["residuals"][2]
    products = jacobian_times(jax_results["constraint Jacobian"][2], V, v_theta)
    pairs = {
        "constraint values": (transcription.split_families(task, residuals), split_stacked(task, reference, g)),
        "Jacobian × v": (
            transcription.split_families(task, products),
            split_stacked(task, reference, cs.mtimes(jac_g, cs.DM(v))),
        ),
    }
    worst = {
        check: max(relative_difference(ours[name], theirs[name]) for name in theirs)
        for check, (ours, theirs) in pairs.items()
    }
    worst["cost"] = relative_difference(residuals.cost, float(f))
    hessian_product = np.asarray(cs.mtimes(hess_f, cs.DM(v))).ravel()
    worst["cost Hessian × v"] = relative_difference(
        cost_hessian_times(jax_results["cost Hessian"][2], V, v_theta), hessian_product
    )
    assert all(value < TOLERANCE for value in worst.values()), f"JAX and CasADi disagree: {worst}"
    return worst


# --------------------------------------------------------------------------------------- report

ROWS = (  # label, JAX function, CasADi Function
    ("constraint residuals and cost", "residuals", "g and f"),
    ("constraint Jacobian", "constraint Jacobian", "jac_g"),
    ("cost Hessian", "cost Hessian", "hess_f"),
    ("constraint Jacobian + cost gradient + cost Hessian", "all blocks", "jac_g, grad_f, hess_f"),
    ("Lagrangian Hessian (upper triangle)", None, "hess_l"),
)


def table(jax_results, casadi_results):
    header = ("quantity", "JAX", "JAX compile", "JAX run", "CasADi", "CasADi build", "CasADi run", "CasADi / JAX")
    lines = [header]
    for label, jax_name, casadi_name in ROWS:
        jax_compile, jax_run, _ = jax_results[jax_name] if jax_name else (None, None, None)
        casadi_build, casadi_run, _ = casadi_results[casadi_name]
        ratio = f"{casadi_run / jax_run:.3g}×" if jax_run else "–"
        lines.append((
            label, jax_name or "–", format_time(jax_compile), format_time(jax_run),
            casadi_name, format_time(casadi_build), format_time(casadi_run), ratio,
        ))  # fmt: skip
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    render = lambda cells: "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    return "\n".join([render(header), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + list(map(render, lines[1:])))


def problem_line(task, nlp, reference, repeats):
    rows = sum(reference.n_stages(name) * size for families in transcription.family_rows(task).values()
               for name, size in families)  # fmt: skip
    return (
        f"take-off, N = {task.n_intervals} ({nlp.n_knots} knots × {nlp.knot_size} variables + "
        f"{nlp.global_size} global = {reference.n_variables} variables, {rows} constraint rows), "
        f"at the published initial guess; run times are medians of {repeats} calls"
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--knots", type=int, default=70, help="N, the number of intervals")
    parser.add_argument("--repeats", type=int, default=7, help="timed runs (the median is reported)")
    args = parser.parse_args()

    logging.getLogger("yourdfpy").setLevel(logging.ERROR)  # unresolved mesh files are irrelevant
    started = time.perf_counter()
    header = machine_lines(("jax", "jaxlib", "numpy", "casadi", "adam-robotics"))
    task = tasks.scenario("take_off", knots=args.knots)
    nlp = transcription.stagewise_nlp(task)
    Z, theta = transcription.to_variables(task, tasks.initial_guess(task))

    log("CasADi ReferenceNLP...")
    urdf_xml = jaxmm.assemble_urdf(jaxmm.robots.ironcub_description()).write_xml_string()
    with tempfile.NamedTemporaryFile(suffix=".urdf") as urdf:
        urdf.write(urdf_xml)
        urdf.flush()
        start = time.perf_counter()
        reference = ReferenceNLP(task, urdf.name)
        reference_build = time.perf_counter() - start
    w0 = np.concatenate([np.ravel(Z), np.asarray(theta)])
    assert np.array_equal(w0, reference.flatten(tasks.initial_guess(task)) / reference.scale())

    rng = np.random.default_rng(SEED)
    expressions = casadi_expressions(reference)
    casadi_results = time_casadi(expressions, w0, rng.normal(size=expressions[1].shape[0]), args.repeats)
    jax_results = time_jax(nlp, Z, theta, args.repeats)
    direction = (jnp.asarray(rng.normal(size=Z.shape)), jnp.asarray(rng.normal(size=theta.shape)))
    worst = agreement(task, reference, jax_results, casadi_results, direction)

    jacobian = jax_results["constraint Jacobian"][1]
    print("\n".join(header))
    print(problem_line(task, nlp, reference, args.repeats))
    print()
    print(table(jax_results, casadi_results))
    print()
    print(
        f"Constraint Jacobian per evaluation: JAX {format_time(jacobian)}, CasADi reference "
        f"{format_time(casadi_results['jac_g'][1])} (ratio {casadi_results['jac_g'][1] / jacobian:.3g}× "
        f"in this run); paper's code {format_time(PAPER_JACOBIAN)} at N = 70; goal ≤ {format_time(GOAL_JACOBIAN)}: "
        + ("met" if jacobian <= GOAL_JACOBIAN else f"not met ({jacobian / GOAL_JACOBIAN:.3g}× over)")
    )
    print(f"CasADi ReferenceNLP construction (ADAM kinematics, per-knot SX Functions): {reference_build:.1f} s")
    print(
        "Checks, max |JAX − CasADi| / max(1, max |CasADi|) over the families (asserted < "
        f"{TOLERANCE:g}): " + ", ".join(f"{name} {value:.1e}" for name, value in worst.items())
    )
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"Total benchmark time {time.perf_counter() - started:.0f} s; load average at the end {load}.")


if __name__ == "__main__":
    main()
