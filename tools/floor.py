"""How fast can an iteration be? The linear algebra's floor for a scenario's Newton matrix on
this machine, and what a second CPU device adds to one solve.

1. The Newton matrix's structure (K = N + 1 blocks of n, the columns the transition rows couple,
   the border of the global variables), filled with random SPD entries, factored and solved by
   ``jaxmm.solver.linalg`` as the solver does: time, FLOP count, rate.
2. The kernels of one block, alone: a GEMM n × n × n, a Cholesky of n, a triangular solve of n
   with s right-hand sides (s coupled columns): their rates bound the factorisation's.
3. The budget: a target solve time over an iteration count is a time per iteration, set
   against one factorisation (the solver needs ≥ 1 per iteration; the inertia correction's
   attempts make it ≈ 2.2 on take-off).
4. ``--devices``: one program on two CPU devices (a subprocess with
   ``--xla_force_host_platform_device_count=2``, which must be set before JAX starts): the
   heaviest knot-parallel derivative, the kinematics' Jacobian and weighted curvature
   (``centroidal_derivatives.centroidal_kinematics_derivatives``) at every knot of the published guess, and
   two independent half-length systems factored, each once on one device and once split
   across the two (``jax.shard_map``). XLA's CPU runtime runs the independent loops of one
   device's program one after the other (measured: two factorisation chains take twice one),
   so a single solve uses one core unless its program is split over devices.
5. ``--knot-size n --coupled s``: steps 1–3 for K blocks of n variables with s coupled columns
   instead of the task's own (K and the border stay the task's): what a transcription with
   fewer variables per knot would leave for the linear algebra, measured rather than
   extrapolated from the FLOP count (``--devices`` still times the task's own structure).

Usage: python tools/floor.py [--scenario take_off] [--knots N] [--iterations 243]
       [--budget 10] [--repeats 15] [--devices] [--knot-size n --coupled s]
"""

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"  # before numpy is imported

import pathlib  # noqa: E402
import sys  # noqa: E402

# benchmarks/machine.py: the machine, versions and tables that the benchmarks print too
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))

import argparse  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def factorisation_flops(K, n, s, m=0):
    """Floating-point operations of ``linalg.factor`` for K blocks of n with s coupled columns
    and a border of m (two-ended: the forward chain's M = K // 2 blocks each need a triangular
    solve of s with n right-hand sides and an n × s × n update, the backward chain's K − 1 − M
    a triangular solve of n with s right-hand sides and an s × n × s update; every block a
    Cholesky; the border, approximately, a block solve with m right-hand sides and its Schur
    complement)."""
    M, back = K // 2, K - 1 - K // 2
    blocks = K * n**3 / 3 + M * (s * s * n + 2 * n * n * s) + back * (n * n * s + 2 * s * s * n)
    border = m * (2 * K * n * n + 2 * K * n * s) + 2 * K * n * m * m + m**3 / 3
    return blocks + border


def random_system(K, n, coupled, m, seed=0):
    """A bordered block-tridiagonal SPD system (D, L, B, C) of that structure: L non-zero in the
    coupled columns only, every block diagonally dominant enough to be positive definite."""
    rng = np.random.default_rng(seed)
    s = len(coupled)
    D = rng.standard_normal((K, n, n)) / np.sqrt(n)
    D = D @ np.swapaxes(D, -1, -2) + 4 * np.eye(n)
    L = np.zeros((K - 1, n, n))
    L[:, :, coupled] = rng.standard_normal((K - 1, n, s)) / np.sqrt(n * s)
    B = rng.standard_normal((K, n, m)) / np.sqrt(K * n)
    C = 4 * np.eye(m)
    return D, L, B, C


def median_time(fn, *args, repeats):
    """(compile + first call [s], median of ``repeats`` later calls [s]) of a jitted fn."""
    import jax

    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return first, float(np.median(times))


def structure(task, knot_size=None, coupled=None):
    """(K, n, coupled columns, m) of a task's condensed Newton matrix, or with n = knot_size and
    its last ``coupled`` columns coupled instead of the task's (K and m the task's)."""
    from jaxmm.solver import rows
    from jaxmm.transcription import nlp as transcription
    from jaxmm import stagewise
    from jaxmm.tasks import initial_guess

    Z, theta = transcription.to_variables(task, initial_guess(task))
    if knot_size is not None:
        return Z.shape[0], knot_size, np.arange(knot_size - coupled, knot_size), theta.shape[0]
    columns = rows.coupled_columns(stagewise.row_supports(transcription.stagewise_nlp(task)))
    n = Z.shape[1]
    columns = np.arange(n) if columns is None else np.asarray(columns, int)
    return Z.shape[0], n, columns, theta.shape[0]


def single_device(args):
    """Print the factorisation's, the kernels' and the budget's tables; return the
    factorisation's median time [s]."""
    import jax
    import jax.numpy as jnp
    from jax.scipy.linalg import solve_triangular

    import jaxmm  # noqa: F401  (float64)
    from jaxmm import tasks
    from jaxmm.solver import linalg
    from machine import format_time, machine_lines, render

    for line in machine_lines(("jax", "jaxlib", "numpy")):
        print(line)
    task = tasks.scenario(args.scenario, knots=args.knots, keep_horizon=args.knots is not None)
    K, n, coupled, m = structure(task, args.knot_size, args.coupled)
    s = coupled.size
    D, L, B, C = (jnp.asarray(a) for a in random_system(K, n, coupled, m))
    factor = jax.jit(lambda D, L, B, C: linalg.factor(D, L, B, C, coupled=tuple(int(i) for i in coupled)))
    solve = jax.jit(linalg.solve)
    compile_f, t_factor = median_time(factor, D, L, B, C, repeats=args.repeats)
    chol = factor(D, L, B, C)
    if not bool(chol.ok):
        sys.exit("the random system did not factor (not positive definite)")
    r, t = jnp.ones((K, n)), jnp.ones(m)
    compile_s, t_solve = median_time(solve, chol, r, t, repeats=args.repeats)
    Ax, Ay = linalg.matvec(D, L, B, C, *solve(chol, r, t))
    residual = max(float(jnp.max(jnp.abs(Ax - r))), float(jnp.max(jnp.abs(Ay - t), initial=0.0)))
    flops = factorisation_flops(K, n, s, m)
    hypothetical = "" if args.knot_size is None else " (--knot-size and --coupled: not the task's own)"
    print(f"\n{args.scenario}, N = {K - 1}: Newton matrix of {K} blocks of {n}, {s} coupled columns, "
          f"border {m}{hypothetical}; solve residual {residual:.1e}\n")
    print(render(("operation", "compile + first call", "median", "GFLOP", "GFLOP/s"), [
        ("factorisation (linalg.factor)", format_time(compile_f), format_time(t_factor), f"{flops / 1e9:.3f}",
         f"{flops / t_factor / 1e9:.1f}"),
        ("block solve (linalg.solve)", format_time(compile_s), format_time(t_solve), "", ""),
    ]))

    rng = np.random.default_rng(1)
    A = jnp.asarray(rng.standard_normal((n, n)))
    S = A @ A.T + n * jnp.eye(n)
    factor_S = jnp.linalg.cholesky(S)
    right = jnp.asarray(rng.standard_normal((n, s)))
    kernels = [
        (f"GEMM {n} × {n} × {n}", jax.jit(lambda a: a @ a), (A,), 2 * n**3),
        (f"Cholesky {n}", jax.jit(jnp.linalg.cholesky), (S,), n**3 / 3),
        (f"triangular solve {n}, {s} right-hand sides", jax.jit(lambda f, b: solve_triangular(f, b, lower=True)),
         (factor_S, right), n * n * s),
    ]
    table, rates = [], []
    for name, fn, inputs, count in kernels:
        _, t_kernel = median_time(fn, *inputs, repeats=10 * args.repeats)
        rates.append(count / t_kernel)
        table.append((name, format_time(t_kernel), f"{count / t_kernel / 1e9:.1f}"))
    print("\nKernels of one block, each alone:\n")
    print(render(("kernel", "median", "GFLOP/s"), table))

    per_iteration = args.budget / args.iterations
    at_gemm = flops / rates[0]  # the GEMM's
    print(f"\nBudget: {args.budget:g} s over {args.iterations} iterations is {format_time(per_iteration)} per iteration.")
    print(render(("per iteration", "time", "× the budget per iteration", f"× {args.iterations} iterations"), [
        ("one factorisation, as measured", format_time(t_factor), f"{t_factor / per_iteration:.2f}",
         format_time(t_factor * args.iterations)),
        ("2.2 factorisations (take-off's mean)", format_time(2.2 * t_factor), f"{2.2 * t_factor / per_iteration:.2f}",
         format_time(2.2 * t_factor * args.iterations)),
        ("one factorisation at the GEMM's rate", format_time(at_gemm), f"{at_gemm / per_iteration:.2f}",
         format_time(at_gemm * args.iterations)),
    ]))
    return t_factor


def parallel_work(task, mesh=None):
    """[(name, jitted fn, inputs)] of the knot-parallel work: the kinematics' Jacobian and
    weighted curvature at every knot of the published guess (an even count: the last repeated
    when odd) and two independent systems of half the Newton matrix's length, factored; with a
    ``mesh`` of two devices each split over them (``jax.shard_map``, the inputs placed so)."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    from jaxmm.rigid_body import centroidal_derivatives as centroidal
    from jaxmm import tasks
    from jaxmm.solver import linalg

    K, n, coupled, m = structure(task)
    robot = task.robot
    frames = robot.contact_frames + robot.jet_frames
    q = tasks.initial_guess(task).knots.configuration
    q = jnp.concatenate([q, q[-1:]]) if q.shape[0] % 2 else q
    rng = np.random.default_rng(2)
    template = centroidal.centroidal_kinematics(robot.model, q[0], frames)
    weights = jax.tree.map(lambda leaf: jnp.asarray(rng.standard_normal(leaf.shape)), template)

    def curvature(q):
        return jax.vmap(lambda qk: centroidal.centroidal_kinematics_derivatives(robot.model, qk, frames, weights)[2])(q)

    half = K // 2
    D, L, B, C = (jnp.asarray(a) for a in random_system(2 * half, n, coupled, m))
    halves = (jnp.stack([D[:half], D[half:]]), jnp.stack([L[: half - 1], L[half:]]), jnp.stack([B[:half], B[half:]]))
    columns = tuple(int(i) for i in coupled)

    def factor_one(D, L, B):
        chol = linalg.factor(D, L, B, C, coupled=columns)
        return chol.forward.blocks, chol.backward.blocks, chol.middle, chol.schur

    names = (f"kinematics' Jacobian and curvature, {q.shape[0]} knots", f"two factorisations of {half} blocks of {n}")
    if mesh is None:
        factor_both = jax.jit(lambda D, L, B: [factor_one(D[k], L[k], B[k]) for k in range(2)])
        return list(zip(names, (jax.jit(curvature), factor_both), ((q,), halves)))
    split = NamedSharding(mesh, P("devices"))

    def on_devices(fn):
        return jax.jit(jax.shard_map(fn, mesh=mesh, in_specs=P("devices"), out_specs=P("devices"), check_vma=False))

    factor_split = on_devices(lambda D, L, B: jax.tree.map(lambda x: x[None], factor_one(D[0], L[0], B[0])))
    return list(zip(names, (on_devices(curvature), factor_split),
                    (jax.device_put((q,), split), jax.device_put(halves, split))))


def two_devices(args):
    """The knot-parallel work timed on two devices: a JSON line {name: median [s]} on stdout."""
    import json

    import jax

    import jaxmm  # noqa: F401  (float64)
    from jaxmm import tasks

    if len(jax.devices()) != 2:
        sys.exit(f"two CPU devices were asked for, JAX has {len(jax.devices())}")
    task = tasks.scenario(args.scenario, knots=args.knots, keep_horizon=args.knots is not None)
    work = parallel_work(task, jax.make_mesh((2,), ("devices",)))
    print(json.dumps({name: median_time(fn, *inputs, repeats=args.repeats)[1] for name, fn, inputs in work}))


def compare_devices(args, t_factor):
    """The knot-parallel work on this process's one device, then on two (a subprocess), and the
    table; t_factor: the whole Newton matrix's factorisation on one device [s]."""
    import json

    from jaxmm import tasks
    from machine import format_time, render

    task = tasks.scenario(args.scenario, knots=args.knots, keep_horizon=args.knots is not None)
    one = {name: median_time(fn, *inputs, repeats=args.repeats)[1] for name, fn, inputs in parallel_work(task)}
    environment = dict(os.environ, XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") +
                                               " --xla_force_host_platform_device_count=2").strip())
    command = [sys.executable, __file__, "--two-device-part", "--scenario", args.scenario,
               "--repeats", str(args.repeats)] + ([] if args.knots is None else ["--knots", str(args.knots)])
    run = subprocess.run(command, env=environment, capture_output=True, text=True)
    if run.returncode != 0:
        sys.exit(f"the two-device part failed (exit {run.returncode}):\n{run.stderr[-4000:]}")
    two = json.loads(run.stdout.strip().splitlines()[-1])
    print("\nThe knot-parallel work in one program on one CPU device (this process), then split over two")
    print("(jax.shard_map, a process with two host devices), same run:\n")
    print(render(("work", "one device", "two devices", "speed-up"),
                 [(name, format_time(one[name]), format_time(two[name]), f"{one[name] / two[name]:.2f}×") for name in one]))
    halves = list(one)[1]
    print(f"\nThe two halves on two devices against the whole matrix's factorisation on one device "
          f"({format_time(t_factor)}): {t_factor / two[halves]:.2f}×.")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="take_off")
    parser.add_argument("--knots", type=int, default=None, help="N (default: the published one)")
    parser.add_argument("--iterations", type=int, default=243, help="iterations of the solve (take-off: 243)")
    parser.add_argument("--budget", type=float, default=10.0, help="target solve time [s]")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--devices", action="store_true", help="also time one program split over two CPU devices")
    parser.add_argument("--knot-size", type=int, default=None, help="n variables per knot instead of the task's")
    parser.add_argument("--coupled", type=int, default=None, help="with --knot-size: s coupled columns (≤ n)")
    parser.add_argument("--two-device-part", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.iterations < 1 or args.budget <= 0 or args.repeats < 1:
        parser.error("--iterations and --repeats must be ≥ 1 and --budget > 0")
    if (args.knot_size is None) != (args.coupled is None):
        parser.error("--knot-size and --coupled go together")
    if args.knot_size is not None and not 1 <= args.coupled <= args.knot_size:
        parser.error(f"--coupled must be in 1..--knot-size ({args.knot_size}), got {args.coupled}")
    if args.two_device_part:
        two_devices(args)
        return
    t_factor = single_device(args)
    if args.devices:
        compare_devices(args, t_factor)


if __name__ == "__main__":
    main()
