"""Time one "kinematics bundle" of iRonCub in jaxmm, Pinocchio and ADAM's JAX backend.

The bundle, per configuration q, is what a multimodal trajectory optimiser needs at each knot:
the centroidal momentum matrix (6 × (6 + 23)), the centre of mass, and the world position and
rotation of 12 frames (the 8 sole corners and the 4 jets). Every library gets the same robot:
the assembled default iRonCub (``jaxmm.load_ironcub``), its neck locked at 0, and the same
seeded random configurations (uniform base position in ±2 m, uniform unit quaternion, joints
uniform within their limits).

What is measured (wall clock; per configuration = median over --repeats runs of a whole batch
of --batch configurations, divided by the batch size; one untimed warm-up run first). The runs
of jaxmm and Pinocchio are interleaved (one run of each in turn), so that their ratios are
measured under the same machine load:

* jaxmm, ``jax.jit`` of one configuration per call (a Python loop over the batch, blocking on
  each result), and ``jax.jit(jax.vmap(...))`` over the batch in one call. Compile time is
  ``jax.jit(f).lower(...).compile()``, i.e. tracing + lowering + XLA compilation.
* Pinocchio from Python: a loop calling ``computeCentroidalMap`` (forward kinematics, CMM and
  CoM), ``centerOfMass`` at the POSITION level (reuses those placements), and
  ``updateFramePlacement(...).homogeneous`` for the 12 frames; no call repeats the kinematics.
* Pinocchio from C++: the same three calls compiled against the installed Pinocchio headers
  and library (needs a C++ compiler and Eigen headers; skipped with a note otherwise). This is
  the cost without the Python bindings.
* ADAM-JAX (mixed velocity representation): CMM, CoM and the pose of one frame (``l_sole_1``)
  as three separate functions, because compiling them together does not finish in reasonable
  time. Each is jitted with one configuration per call, jitted with the whole batch in one call
  (ADAM's own batching over leading dimensions: ``jax.vmap`` over ADAM 0.5 fails with this jax),
  and run eagerly (--eager-repeats calls on one configuration), each in a subprocess killed
  after --budget seconds (counted from the end of its setup). The ADAM bundle is estimated as
  CMM + CoM + 12 × frame, and given as a lower bound (≥) when a part did not finish.

The run asserts that jaxmm and Pinocchio agree (< 1e-9) on the CMM, CoM and frame poses at
every benchmark configuration, so both compute the same quantities; ADAM's eager results at
one configuration are compared with jaxmm's and the differences printed.

Usage: python benchmarks/rigid_body.py [--budget 120] [--batch 1024] [--repeats 7]
"""

import os

os.environ["OPENBLAS_NUM_THREADS"] = "1"  # before numpy is imported

import argparse  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import pathlib  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pinocchio as pin  # noqa: E402

import jaxmm  # noqa: E402  (enables float64)
from machine import format_time, log, machine_lines  # noqa: E402

FRAMES = (
    "l_sole_1", "l_sole_2", "l_sole_3", "l_sole_4",
    "r_sole_1", "r_sole_2", "r_sole_3", "r_sole_4",
    "l_arm_jet_turbine", "r_arm_jet_turbine", "chest_l_jet_turbine", "chest_r_jet_turbine",
)  # fmt: skip
ADAM_FRAME = "l_sole_1"
ADAM_PARTS = ("CMM", "CoM", f"frame {ADAM_FRAME}")
ADAM_MODES = {
    "jit": "jit, 1 config/call",
    "batch": "jit, batched inputs",
    "eager": "eager (no jit)",
}
SEED = 0
TOLERANCE = 1e-9

CPP_SOURCE = r"""
#include <pinocchio/multibody.hpp>
#include <pinocchio/serialization.hpp>
#include <pinocchio/algorithm/center-of-mass.hpp>
#include <pinocchio/algorithm/centroidal.hpp>
#include <pinocchio/algorithm/frames.hpp>
#include <chrono>
#include <fstream>
#include <iostream>
#include <vector>

// argv: model.bin configurations.f64 frame_id... ; prints the seconds of one pass over all
// configurations, after an untimed warm-up pass.
int main(int argc, char ** argv) {
  pinocchio::Model model;
  model.loadFromBinary(argv[1]);
  pinocchio::Data data(model);
  std::ifstream file(argv[2], std::ios::binary | std::ios::ate);
  const std::size_t count = file.tellg() / sizeof(double) / model.nq;
  std::vector<double> values(count * model.nq);
  file.seekg(0);
  file.read(reinterpret_cast<char *>(values.data()), values.size() * sizeof(double));
  std::vector<Eigen::VectorXd> configurations;
  for (std::size_t i = 0; i < count; ++i)
    configurations.push_back(Eigen::Map<const Eigen::VectorXd>(values.data() + i * model.nq, model.nq));
  std::vector<pinocchio::FrameIndex> frames;
  for (int i = 3; i < argc; ++i) frames.push_back(std::atoi(argv[i]));

  double sink = 0.0;  // keeps the results observable
  std::chrono::duration<double> elapsed;
  for (int pass = 0; pass < 2; ++pass) {
    const auto start = std::chrono::steady_clock::now();
    for (const auto & q : configurations) {
      pinocchio::computeCentroidalMap(model, data, q);
      pinocchio::centerOfMass(model, data, pinocchio::POSITION, false);
      for (const auto frame : frames) sink += pinocchio::updateFramePlacement(model, data, frame).translation()[0];
      sink += data.Ag(0, 0) + data.com[0][0];
    }
    elapsed = std::chrono::steady_clock::now() - start;
  }
  std::cout << elapsed.count() << " " << sink << std::endl;
}
"""
CPP_DEFINES = (  # from Pinocchio's exported CMake targets
    "-DBOOST_MPL_LIMIT_LIST_SIZE=30",
    "-DBOOST_MPL_LIMIT_VECTOR_SIZE=30",
    "-DBOOST_MPL_CFG_NO_PREPROCESSED_HEADERS",
    "-DBOOST_FUSION_INVOKE_MAX_ARITY=12",
    "-DPINOCCHIO_ENABLE_TEMPLATE_INSTANTIATION",
)


def timed(run):
    """A measurement: calls run() and returns its wall time [s]."""

    def measure():
        start = time.perf_counter()
        run()
        return time.perf_counter() - start

    return measure


def interleaved_medians(measures, repeats):
    """{name: median seconds} of each measurement, after one untimed warm-up of each; the
    repeats take turns (a, b, a, b, ...) so that all see the same machine load."""
    for measure in measures.values():
        measure()
    times = {name: [] for name in measures}
    for _ in range(repeats):
        for name, measure in measures.items():
            times[name].append(measure())
    return {name: statistics.median(values) for name, values in times.items()}


def median_seconds(run, repeats):
    """Median wall time of run() over repeats calls, after one untimed warm-up call."""
    return interleaved_medians({"run": timed(run)}, repeats)["run"]


def cpu_per_wall_second(run, repeats):
    """Process CPU time over wall time of repeats calls of run(): the number of busy cores."""
    cpu, wall = time.process_time(), time.perf_counter()
    for _ in range(repeats):
        run()
    return (time.process_time() - cpu) / (time.perf_counter() - wall)


def compile_seconds(function, *args):
    """(seconds to trace, lower and compile, compiled function)."""
    start = time.perf_counter()
    compiled = jax.jit(function).lower(*args).compile()
    return time.perf_counter() - start, compiled


def random_configurations(model, count, seed):
    """(count, 7 + n) configurations: base in ±2 m, uniform unit quaternion, joints in limits."""
    rng = np.random.default_rng(seed)
    lower = np.maximum(np.asarray(model.position_limits[:, 0]), -np.pi)
    upper = np.minimum(np.asarray(model.position_limits[:, 1]), np.pi)
    quaternions = rng.normal(size=(count, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
    joints = rng.uniform(lower, upper, (count, model.n_joints))
    return np.concatenate([rng.uniform(-2, 2, (count, 3)), quaternions, joints], axis=1)


# ---------------------------------------------------------------------------------------- jaxmm


def jaxmm_bundle(model, q):
    positions, rotations = jaxmm.frame_poses(model, q, FRAMES)
    return jaxmm.centroidal_momentum_matrix(model, q), jaxmm.com_position(model, q), positions, rotations


def compile_jaxmm(model, Q):
    """({row key: compile seconds}, {row key: batch run}, batched outputs) for jit with one
    configuration per call (a loop over the batch) and jit(vmap) over the batch."""
    single = lambda q: jaxmm_bundle(model, q)  # noqa: E731  (the model is a constant, as in use)
    Q_device = jnp.asarray(Q)
    configurations = list(Q_device)
    single_key, batch_key = ("jaxmm", "jit, 1 config/call"), ("jaxmm", f"jit(vmap), batch {len(Q)}")
    single_compile, single_compiled = compile_seconds(single, configurations[0])
    batch_compile, batch_compiled = compile_seconds(jax.vmap(single), Q_device)
    runs = {
        single_key: lambda: [jax.block_until_ready(single_compiled(q)) for q in configurations],
        batch_key: lambda: jax.block_until_ready(batch_compiled(Q_device)),
    }
    outputs = [np.asarray(x) for x in batch_compiled(Q_device)]
    return {single_key: single_compile, batch_key: batch_compile}, runs, outputs


# ------------------------------------------------------------------------------------ Pinocchio


class PinocchioRobot:
    """The same robot in Pinocchio (neck locked), with jaxmm's q mapped to Pinocchio's."""

    def __init__(self, model, urdf_xml):
        full = pin.buildModelFromXML(urdf_xml, pin.JointModelFreeFlyer())
        reference = pin.neutral(full)
        locked = [full.getJointId(name) for name in model.locked_joint_names]
        for joint, value in zip(locked, np.asarray(model.locked_positions)):
            reference[full.joints[joint].idx_q] = value
        self.model = pin.buildReducedModel(full, locked, reference)
        self.data = self.model.createData()
        joints = [self.model.joints[self.model.getJointId(name)] for name in model.joint_names]
        self.q_index = [joint.idx_q for joint in joints]
        self.v_index = [joint.idx_v for joint in joints]
        self.frame_ids = [self.model.getFrameId(name, pin.BODY) for name in FRAMES]

    def configurations(self, Q):
        """(count, nq) Pinocchio configurations: (p, quaternion x y z w, its joint order)."""
        Q_pin = np.zeros((len(Q), self.model.nq))
        Q_pin[:, :7] = Q[:, :7]
        Q_pin[:, self.q_index] = Q[:, 7:]
        return Q_pin

    def bundle(self, q):
        """CMM (Pinocchio's base-local velocity), CoM and 12 frame placements (4 × 4)."""
        model, data = self.model, self.data
        cmm = pin.computeCentroidalMap(model, data, q)  # also the placements and data.com[0]
        com = pin.centerOfMass(model, data, pin.KinematicLevel.POSITION, False)
        poses = [pin.updateFramePlacement(model, data, frame).homogeneous for frame in self.frame_ids]
        return cmm, com, poses

    def mixed_cmm(self, cmm, q):
        """Pinocchio's CMM for jaxmm's mixed velocity ν = (ṗ, ω world, ṡ), jaxmm's joint order.

        Pinocchio's free-flyer velocity is (Rᵀṗ, Rᵀω), hence the right product by Rᵀ.
        """
        R = pin.Quaternion(q[3:7]).toRotationMatrix()  # Pinocchio stores (x, y, z, w)
        return np.concatenate([cmm[:, :3] @ R.T, cmm[:, 3:6] @ R.T, cmm[:, self.v_index]], axis=1)


def check_agreement(robot, Q_pin, jaxmm_outputs):
    """Largest |jaxmm − Pinocchio| over all configurations for CMM, CoM and frame poses."""
    cmm, com, positions, rotations = jaxmm_outputs
    worst = dict(CMM=0.0, CoM=0.0, frames=0.0)
    for k, q in enumerate(Q_pin):
        cmm_pin, com_pin, poses = robot.bundle(q)
        poses = np.asarray(poses)
        worst["CMM"] = max(worst["CMM"], np.abs(robot.mixed_cmm(cmm_pin, q) - cmm[k]).max())
        worst["CoM"] = max(worst["CoM"], np.abs(com_pin - com[k]).max())
        frames = max(np.abs(poses[:, :3, 3] - positions[k]).max(), np.abs(poses[:, :3, :3] - rotations[k]).max())
        worst["frames"] = max(worst["frames"], frames)
    assert all(value < TOLERANCE for value in worst.values()), f"jaxmm and Pinocchio disagree: {worst}"
    return worst


def build_pinocchio_cpp(robot, Q_pin, directory):
    """(measurement, None) where the measurement runs the compiled C++ loop over the batch and
    returns its seconds, or (None, why it is skipped)."""
    compiler = shutil.which("c++") or shutil.which("g++")
    prefix = next((p for p in pathlib.Path(pin.__file__).parents if (p / "include" / "pinocchio").is_dir()), None)
    eigen_candidates = ([prefix / "include" / "eigen3"] if prefix else []) + [
        pathlib.Path("/usr/include/eigen3"),
        pathlib.Path("/usr/local/include/eigen3"),
    ]
    eigen = next((d for d in eigen_candidates if d.is_dir()), None)
    if compiler is None or prefix is None or eigen is None:
        return None, "needs a C++ compiler, Pinocchio's headers and Eigen's headers"
    source, binary = directory / "pinocchio_bundle.cpp", directory / "pinocchio_bundle"
    source.write_text(CPP_SOURCE)
    robot.model.saveToBinary(str(directory / "model.bin"))
    np.ascontiguousarray(Q_pin, dtype=np.float64).tofile(directory / "configurations.f64")
    command = [
        compiler, "-std=c++17", "-O3", "-DNDEBUG", *CPP_DEFINES, str(source), "-o", str(binary),
        f"-I{prefix / 'include'}", f"-I{eigen}", f"-L{prefix / 'lib'}", f"-Wl,-rpath,{prefix / 'lib'}",
        "-lpinocchio_default", "-lboost_serialization", "-lboost_filesystem",
    ]  # fmt: skip
    built = subprocess.run(command, capture_output=True, text=True)
    if built.returncode != 0:
        return None, "compilation failed: " + (built.stderr.strip().splitlines() or ["?"])[-1]
    frames = [str(frame) for frame in robot.frame_ids]
    run = [str(binary), str(directory / "model.bin"), str(directory / "configurations.f64"), *frames]
    return lambda: float(subprocess.run(run, capture_output=True, text=True, check=True).stdout.split()[0]), None


# ----------------------------------------------------------------------------------------- ADAM


def adam_function(kin_dyn, part):
    return {
        "CMM": kin_dyn.centroidal_momentum_matrix,
        "CoM": kin_dyn.CoM_position,
        f"frame {ADAM_FRAME}": lambda H, s: kin_dyn.forward_kinematics(ADAM_FRAME, H, s),
    }[part]


def adam_worker(directory, part, mode, repeats):
    """Subprocess body: set up ADAM, print "ready", time one part in one mode.

    Results go to a JSON-lines file as soon as they are known, so that a compile time
    survives the kill when the timed runs exceed the budget.
    """
    from adam.core.constants import Representations
    from adam.jax import KinDynComputations

    directory = pathlib.Path(directory)
    saved = np.load(directory / "adam_inputs.npz")
    kin_dyn = KinDynComputations(str(directory / "ironcub.urdf"), [str(j) for j in saved["joints"]])
    kin_dyn.set_frame_velocity_representation(Representations.MIXED_REPRESENTATION)
    function = adam_function(kin_dyn, part)
    H, S = jnp.asarray(saved["H"]), jnp.asarray(saved["s"])
    with open(adam_results_path(directory, part, mode), "w") as results:
        report = lambda **result: print(json.dumps(result), file=results, flush=True)  # noqa: E731
        print("ready", flush=True)
        if mode == "eager":
            report(run=median_seconds(lambda: jax.block_until_ready(function(H[0], S[0])), repeats))
            report(value=np.asarray(function(H[0], S[0])).tolist())
        elif mode == "jit":
            seconds, compiled = compile_seconds(function, H[0], S[0])
            report(compile=seconds)
            pairs = list(zip(H, S))
            run = median_seconds(lambda: [jax.block_until_ready(compiled(h, s)) for h, s in pairs], repeats)
            report(run=run / len(pairs))
        else:  # ADAM batches natively; jax.vmap over ADAM 0.5 fails with jax 0.10 (sharding spec)
            seconds, compiled = compile_seconds(function, H, S)
            report(compile=seconds)
            report(run=median_seconds(lambda: jax.block_until_ready(compiled(H, S)), repeats) / len(H))


def adam_results_path(directory, part, mode):
    return directory / f"adam {part} {mode}.jsonl"


def run_adam(directory, part, mode, repeats, budget):
    """What the worker measured within budget seconds of its setup: a dict with "compile" and
    "run" seconds (and "value" when eager), missing the entries it did not reach."""
    command = [sys.executable, __file__, "--adam-worker", str(directory), part, mode, "--repeats", str(repeats)]
    with open(directory / "adam_worker.log", "a") as errors:
        with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=errors, text=True) as process:
            for line in process.stdout:  # the budget starts once the worker is set up
                if line.strip() == "ready":
                    break
            try:
                process.wait(timeout=budget)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
    if process.returncode > 0:  # negative when killed at the budget
        errors = (directory / "adam_worker.log").read_text().strip().splitlines()
        raise RuntimeError(f"ADAM worker {part}/{mode} failed: {errors[-1] if errors else process.returncode}")
    result = {}
    for line in adam_results_path(directory, part, mode).read_text().splitlines():
        result.update(json.loads(line))
    return result


def time_adam(robot, Q, urdf_xml, args, directory):
    """{(part, mode): result} for every ADAM part and mode, each in its own subprocess."""
    (directory / "ironcub.urdf").write_bytes(urdf_xml)
    rotations = jax.vmap(jaxmm.rigid_body.so3.quaternion_to_rotation)(jnp.asarray(Q[:, 3:7]))
    H = np.tile(np.eye(4), (len(Q), 1, 1))
    H[:, :3, :3], H[:, :3, 3] = np.asarray(rotations), Q[:, :3]
    np.savez(directory / "adam_inputs.npz", H=H, s=Q[:, 7:], joints=np.array(robot.model.joint_names))
    results = {}
    for mode in ADAM_MODES:
        repeats = args.eager_repeats if mode == "eager" else args.repeats
        for part in ADAM_PARTS:
            log(f"ADAM-JAX {part}, {ADAM_MODES[mode]} (budget {args.budget:g} s)...")
            start = time.perf_counter()
            results[part, mode] = run_adam(directory, part, mode, repeats, args.budget)
            finished = "run" in results[part, mode]
            log(f"  {'done' if finished else 'did not finish'} after {time.perf_counter() - start:.0f} s")
    return results


def adam_rows(results, budget):
    """Table rows: each part in each mode, then the bundle estimate CMM + CoM + 12 × frame.

    A part that did not finish contributes nothing to the bundle, which is then a lower bound.
    """
    late = f"did not finish in {budget:g} s"
    rows = []
    for mode, label in ADAM_MODES.items():
        parts = [results[part, mode] for part in ADAM_PARTS]
        for part, result in zip(ADAM_PARTS, parts):
            if mode == "eager":
                compiled, run = None, result.get("run", late)
            elif "compile" not in result:
                compiled, run = late, None
            else:
                compiled, run = result["compile"], result.get("run", late)
            rows.append((f"ADAM-JAX {part}", label, compiled, run))
        weights = (1, 1, len(FRAMES))
        run = sum(w * r["run"] for w, r in zip(weights, parts) if "run" in r)
        bundle_run = run if all("run" in r for r in parts) else ("≥", run)
        bundle_compile = None
        if mode != "eager":
            known = sum(r.get("compile", budget) for r in parts)
            bundle_compile = known if all("compile" in r for r in parts) else f"> {known:.0f} s"
        rows.append((f"ADAM-JAX bundle (CMM + CoM + {len(FRAMES)} × frame)", label, bundle_compile, bundle_run))
    return rows


def adam_agreement(results, jaxmm_outputs):
    """Largest |ADAM − jaxmm| at the first configuration, from the eager runs.

    Expect ~1e-7 on the CMM: ADAM uses the URDF's joint axes as written, and iCub's shoulder
    axes have norm 1 + 1.6e-7; jaxmm and Pinocchio normalise them.
    """
    cmm, com, positions, rotations = (x[0] for x in jaxmm_outputs)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotations[FRAMES.index(ADAM_FRAME)], positions[FRAMES.index(ADAM_FRAME)]
    expected = dict(zip(ADAM_PARTS, (cmm, com, pose)))
    return {
        part: float(np.abs(np.asarray(results[part, "eager"]["value"]) - expected[part]).max())
        for part in ADAM_PARTS
        if "value" in results[part, "eager"]
    }


# --------------------------------------------------------------------------------------- report


def format_cell(value):
    """A duration, or a (prefix, duration) pair, or a string as is."""
    if isinstance(value, str):
        return value
    if isinstance(value, tuple):
        return f"{value[0]} {format_time(value[1])}"
    return format_time(value)


def format_compile(value):
    return value if value is None or isinstance(value, str) else f"{value:.1f} s"


def speedup(value, reference):
    """How many times faster the reference (jaxmm vmap) is than this row, to 3 digits."""
    if value is None or isinstance(value, str):
        return "–"
    if isinstance(value, tuple):
        return f"{value[0]} {speedup(value[1], reference)}"
    ratio = float(f"{value / reference:.3g}")
    return f"{ratio:,.0f}×" if ratio >= 100 else f"{ratio:g}×"


def table(rows, reference):
    header = ("implementation", "mode", "compile", "per configuration", "jaxmm vmap is … faster")
    lines = [header] + [
        (name, mode, format_compile(compiled) or "–", format_cell(run), speedup(run, reference))
        for name, mode, compiled, run in rows
    ]
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    render = lambda cells: "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    return "\n".join([render(header), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + list(map(render, lines[1:])))


def goal_lines(rows, cpp, compile_time, reference):
    by_name = {(name, mode): run for name, mode, _, run in rows}
    python_loop = by_name["Pinocchio", "Python loop"]
    lines = [
        "Goals (ratios measured in this run; > 1× means jaxmm vmap is faster per configuration):",
        f"- vs Pinocchio, Python loop: {python_loop / reference:.2f}× (goal ≥ 1×)",
    ]
    if cpp is not None:
        lines.append(f"- vs Pinocchio, C++ loop:    {cpp / reference:.2f}× (goal ≥ 1×)")
    for mode, label in ADAM_MODES.items():
        run = by_name[f"ADAM-JAX bundle (CMM + CoM + {len(FRAMES)} × frame)", label]
        lines.append(f"- vs ADAM-JAX bundle, {label}: {speedup(run, reference)} (goal ≥ 10×)")
    lines.append(f"- jaxmm compile (jit(vmap) of the bundle): {compile_time:.1f} s (goal < 20 s)")
    return lines


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--budget", type=float, default=120.0, help="seconds allowed per ADAM subprocess")
    parser.add_argument("--batch", type=int, default=1024, help="configurations per batch")
    parser.add_argument("--repeats", type=int, default=7, help="timed runs (the median is reported)")
    parser.add_argument("--eager-repeats", type=int, default=3, help="timed eager ADAM calls")
    parser.add_argument("--adam-worker", nargs=3, metavar=("DIR", "PART", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.adam_worker:
        adam_worker(*args.adam_worker, args.repeats)
        return

    logging.getLogger("yourdfpy").setLevel(logging.ERROR)  # unresolved mesh files are irrelevant
    started = time.perf_counter()
    header = machine_lines(("jax", "jaxlib", "numpy", "pin", "adam-robotics"))
    robot = jaxmm.load_ironcub()
    urdf_xml = jaxmm.assemble_urdf(jaxmm.robots.ironcub_description()).write_xml_string()
    Q = random_configurations(robot.model, args.batch, SEED)

    log("jaxmm (compiling)...")
    compile_times, runs, jaxmm_outputs = compile_jaxmm(robot.model, Q)
    measures = {key: timed(run) for key, run in runs.items()}
    pinocchio = PinocchioRobot(robot.model, urdf_xml)
    Q_pin = pinocchio.configurations(Q)
    agreement = check_agreement(pinocchio, Q_pin, jaxmm_outputs)
    configurations = list(Q_pin)
    measures["Pinocchio", "Python loop"] = timed(lambda: [pinocchio.bundle(q) for q in configurations])
    with tempfile.TemporaryDirectory(prefix="jaxmm-benchmark-") as scratch:
        directory = pathlib.Path(scratch)
        log("Pinocchio C++ (compiling)...")
        cpp_measure, cpp_skipped = build_pinocchio_cpp(pinocchio, Q_pin, directory)
        if cpp_measure is not None:
            measures["Pinocchio", "C++ loop"] = cpp_measure
        log("jaxmm and Pinocchio, interleaved...")
        medians = interleaved_medians(measures, args.repeats)
        batch_key = ("jaxmm", f"jit(vmap), batch {args.batch}")
        cores_used = cpu_per_wall_second(runs[batch_key], args.repeats)
        adam = time_adam(robot, Q, urdf_xml, args, directory)
    rows = [(*key, compile_times.get(key), seconds / args.batch) for key, seconds in medians.items()]
    if cpp_measure is None:
        rows.append(("Pinocchio", "C++ loop", None, f"skipped: {cpp_skipped}"))
    rows += adam_rows(adam, args.budget)
    reference, vmap_compile = medians[batch_key] / args.batch, compile_times[batch_key]
    cpp = medians["Pinocchio", "C++ loop"] / args.batch if cpp_measure is not None else None
    adam_check = adam_agreement(adam, jaxmm_outputs)

    print("\n".join(header))
    print(
        f"iRonCub ({robot.model.nq} q, {robot.model.nv} ν); bundle = CMM (6 × {robot.model.nv}) + CoM + "
        f"poses of {len(FRAMES)} frames; batch {args.batch}, median of {args.repeats} runs "
        f"(ADAM eager: {args.eager_repeats}), ADAM budget {args.budget:g} s per measurement"
    )
    print()
    print(table(rows, reference))
    print()
    print("\n".join(goal_lines(rows, cpp, vmap_compile, reference)))
    print()
    print(
        "Checks: max |jaxmm − Pinocchio| over the batch: "
        + ", ".join(f"{k} {v:.1e}" for k, v in agreement.items())
        + f" (asserted < {TOLERANCE:g}); max |ADAM − jaxmm| at one configuration: "
        + (", ".join(f"{k} {v:.1e}" for k, v in adam_check.items()) or "–")
        + " (ADAM does not normalise the URDF's slightly non-unit shoulder axes)"
    )
    print(f"jaxmm jit(vmap) kept {cores_used:.2f} cores busy on average (process CPU time / wall time).")
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"Total benchmark time {time.perf_counter() - started:.0f} s; load average at the end {load}.")


if __name__ == "__main__":
    main()
