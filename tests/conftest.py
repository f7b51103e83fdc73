"""Shared fixtures: the robots under test and their Pinocchio twins.

Pinocchio is the independent reference. Its free-flyer velocity is expressed in the base
frame (v_local = Rᵀṗ, ω_local = Rᵀω); ``PinocchioTwin.velocity`` converts our mixed ν to it
rather than loosening any tolerance.
"""

import gc
import os
import pathlib


def _pin_xdist_worker():
    """Give each xdist worker its own cores, before JAX starts its thread pool.

    Two unpinned JAX processes on the same cores are not 2x slower each but up to 85x (measured
    here: a 0.16 s jitted loop took 14 s with a second copy running beside it; pinned to separate
    cores, 0.2 s each): XLA's worker threads spin waiting for work and starve each other.
    Notebook kernels started by a worker inherit its cores.
    """
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if not worker or not hasattr(os, "sched_setaffinity"):
        return
    cores = sorted(os.sched_getaffinity(0))
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > len(cores):
        return  # some workers would share a core whatever we do
    index = int(worker.removeprefix("gw")) % workers  # a worker replacing a crashed one is gw2, gw3, …
    os.sched_setaffinity(0, set(cores[index::workers]))


_pin_xdist_worker()
# A size limit turns on the file lock of JAX's persistent compilation cache; without it a process
# can read an executable another process is still writing (seen: an xdist worker aborted in
# deserialising a half-written entry). Set in the environment so notebook kernels and
# subprocesses share it; .ci/run sets it for its main job too (entries need the same bookkeeping).
os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(16 << 30))
# The suite compiles far more than it runs: at XLA's lowest backend optimisation and without its
# MLIR fusion emitters, a small problem's solve compiles about 3.5x faster and take-off at
# N = 14 about 2.4x faster, for a solve about 3x slower, with the same optimum
# (docs/design-decisions.md, "XLA's lowest backend optimisation in the tests"). Set before JAX starts, and so for notebook kernels too; .ci/run
# sets the same for its main job, whose compiled programs the tests then load (the flags are part
# of the persistent cache's key). Results change only by rounding; speed is measured in
# benchmarks/, which use XLA's defaults.
TEST_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
if TEST_XLA_FLAGS not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {TEST_XLA_FLAGS}".strip()

import jax  # noqa: E402  (after the pinning: JAX's threads inherit the affinity)
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jaxmm  # noqa: E402
from jaxmm import compilation  # noqa: E402
from jaxmm.rigid_body import so3  # noqa: E402

# Compiled programs persist on disk, so the test processes (xdist workers, notebook kernels) that
# solve the same problem structure compile it once per run (and once per machine, across runs).
CACHE = os.environ.setdefault(
    "JAX_COMPILATION_CACHE_DIR", str(pathlib.Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax")
)
jax.config.update("jax_compilation_cache_dir", CACHE)

SHARED = pathlib.Path(os.environ.get("JAXMM_SHARED", pathlib.Path(__file__).resolve().parents[2] / "shared"))
IRONCUB_URDF = SHARED / "robots" / "ironcub-mk1_1" / "model.urdf"


class PinocchioTwin:
    """A Pinocchio model of the same URDF with the same locked joints, and q/ν converters."""

    def __init__(self, model, urdf_xml):
        import pinocchio as pin

        self.pin = pin
        full = pin.buildModelFromXML(urdf_xml, pin.JointModelFreeFlyer())
        locked = [full.getJointId(name) for name in model.locked_joint_names]
        reference = pin.neutral(full)
        for name, value in zip(model.locked_joint_names, np.asarray(model.locked_positions)):
            reference[full.joints[full.getJointId(name)].idx_q] = value
        self.model = pin.buildReducedModel(full, locked, reference) if locked else full
        self.data = self.model.createData()
        self.q_index = [self.model.joints[self.model.getJointId(n)].idx_q for n in model.joint_names]
        # Continuous joints are (cos, sin) pairs in Pinocchio.
        self.unbounded = [self.model.joints[self.model.getJointId(n)].nq == 2 for n in model.joint_names]
        self.v_index = [self.model.joints[self.model.getJointId(n)].idx_v for n in model.joint_names]

    def configuration(self, q):
        q = np.asarray(q)
        q_pin = np.zeros(self.model.nq)
        q_pin[:7] = q[:7]  # Pinocchio's free flyer is also (p, quaternion x y z w)
        for index, unbounded, angle in zip(self.q_index, self.unbounded, q[7:]):
            if unbounded:
                q_pin[index : index + 2] = np.cos(angle), np.sin(angle)
            else:
                q_pin[index] = angle
        return q_pin

    def velocity(self, q, nu):
        nu = np.asarray(nu)
        R = np.asarray(so3.quaternion_to_rotation(np.asarray(q)[3:7]))
        v_pin = np.zeros(self.model.nv)
        v_pin[:3] = R.T @ nu[:3]
        v_pin[3:6] = R.T @ nu[3:6]
        v_pin[self.v_index] = nu[6:]
        return v_pin

    def velocity_map(self, q):
        """T (nv_pin, 6 + n) with ν_pin = T ν: the base's linear and angular velocity in the base
        frame (Pinocchio's free flyer), the joints in Pinocchio's order. Generalised forces map
        back as τ = Tᵀ τ_pin, the mass matrix as M = Tᵀ M_pin T."""
        R = np.asarray(so3.quaternion_to_rotation(np.asarray(q)[3:7]))
        T = np.zeros((self.model.nv, 6 + len(self.v_index)))
        T[:3, :3] = T[3:6, 3:6] = R.T
        T[self.v_index, 6 + np.arange(len(self.v_index))] = 1.0
        return T

    def acceleration(self, q, nu, nu_dot):
        """a_pin = d/dt (T ν) = T ν̇ + Ṫ ν, with Ṙᵀ = −Rᵀ S(ω): the linear part gains −Rᵀ (ω × ṗ)
        and the angular part nothing (Rᵀ S(ω) ω = 0)."""
        nu = np.asarray(nu)
        a_pin = self.velocity_map(q) @ np.asarray(nu_dot)
        a_pin[:3] -= self.velocity_map(q)[:3, :3] @ np.cross(nu[3:6], nu[:3])
        return a_pin

    def external_forces(self, q, frames, forces):
        """Pinocchio's fext for pure world forces (k, 3) at the origins of frames (names): per
        joint, the sum of the forces' spatial forces in the joint's local frame."""
        pin = self.pin
        pin.framesForwardKinematics(self.model, self.data, self.configuration(q))
        fext = [pin.Force.Zero() for _ in range(self.model.njoints)]
        for name, force in zip(frames, np.asarray(forces)):
            fid = self.frame_id(name)
            joint = self.model.frames[fid].parentJoint
            world = pin.Force(force, np.cross(self.data.oMf[fid].translation, force))
            fext[joint] = fext[joint] + self.data.oMi[joint].actInv(world)
        return fext

    def frame_id(self, name):
        return self.model.getFrameId(name, self.pin.BODY)


def random_configurations(model, count, seed):
    """Random q: base anywhere within 2 m, random unit quaternion, joints within limits
    (within ±π for unlimited joints). Returns (count, 7 + n)."""
    rng = np.random.default_rng(seed)
    lower = np.maximum(np.asarray(model.position_limits[:, 0]), -np.pi)
    upper = np.minimum(np.asarray(model.position_limits[:, 1]), np.pi)
    quaternions = rng.normal(size=(count, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
    return np.concatenate(
        [rng.uniform(-2, 2, (count, 3)), quaternions, rng.uniform(lower, upper, (count, model.n_joints))],
        axis=1,
    )


def assert_kinematics_derivatives_equal_autodiff(model, frames, configurations, seed):
    """``centroidal_derivatives.centroidal_kinematics_derivatives`` (the tree recursions) against
    the plain kinematics differentiated by JAX: the kinematics, their Jacobian (``jax.jacfwd``, and
    through ``centroidal_kinematics``' own forward-mode rule) and the curvature of a random weighted
    sum (``jax.hessian``), at each configuration. The kinematics are affine in the base position,
    whose rows and columns of the curvature are zero."""
    from jaxmm.rigid_body import centroidal_derivatives

    indices = np.asarray(model.frame_indices(frames), int)

    def bundle(q):  # the same quantities from the public, separately differentiated functions
        positions, rotations = jaxmm.frame_poses(model, q)
        return dict(com=jaxmm.com_position(model, q), cmm=jaxmm.centroidal_momentum_matrix(model, q),
                    frame_positions=positions[indices], frame_rotations=rotations[indices])

    rng = np.random.default_rng(seed)
    weights = jax.tree.map(lambda s: jax.numpy.asarray(rng.normal(size=s.shape)),
                           jax.eval_shape(bundle, configurations[0]))

    def weighted(q):
        out = bundle(q)
        return sum(jax.numpy.sum(w * v) for w, v in zip(jax.tree.leaves(weights), jax.tree.leaves(out)))

    fused = jax.jit(lambda q: centroidal_derivatives.centroidal_kinematics_derivatives(model, q, frames, weights))
    plain = jax.jit(lambda q: (bundle(q), jax.jacfwd(bundle)(q), jax.hessian(weighted)(q)))
    through_rule = jax.jit(jax.jacfwd(lambda q: centroidal_derivatives.centroidal_kinematics(model, q, frames)))
    for q in configurations:
        (kinematics, jacobian, curvature), (kinematics_ref, jacobian_ref, hessian) = fused(q), plain(q)
        for a, b in zip(jax.tree.leaves((kinematics, jacobian, through_rule(q))),
                        jax.tree.leaves((kinematics_ref, jacobian_ref, jacobian_ref))):
            assert a.shape == b.shape and np.abs(a - b).max() <= 1e-12 * max(1.0, np.abs(b).max())
        assert np.abs(curvature - hessian).max() <= 1e-11 * np.abs(hessian).max()
        assert np.abs(curvature[:3]).max() == 0.0 and np.abs(curvature[:, :3]).max() == 0.0
        assert np.abs(hessian[:3]).max() <= 1e-10 * np.abs(hessian).max()  # affine in the base position


def _ironcub_real():
    default = jaxmm.load_ironcub()
    model = jaxmm.model_from_urdf(
        IRONCUB_URDF, joints=default.model.joint_names, check_inertia=False
    )  # the public URDF has non-physical elbow inertias; Pinocchio loads them too
    return model, IRONCUB_URDF.read_text()


def _ironcub_assembled():
    description = jaxmm.robots.ironcub_description()
    urdf = jaxmm.assemble_urdf(description)
    return jaxmm.load_ironcub().model, urdf.write_xml_string()


# The real iRonCub URDF lives in ../shared (CI has it) and is not part of the project: without it
# the checks run on the assembled default robot alone, which the project always has.
ROBOTS = ["ironcub (assembled default)"] + (["ironcub-mk1_1 (shared URDF)"] if IRONCUB_URDF.is_file() else [])


@pytest.fixture(scope="session", params=ROBOTS)
def robot_pair(request):
    """(jaxmm Model, PinocchioTwin) for the assembled default robot, and the real iRonCub URDF
    where ``../shared`` has it."""
    model, xml = _ironcub_real() if request.param.startswith("ironcub-mk1_1") else _ironcub_assembled()
    return model, PinocchioTwin(model, xml)


@pytest.fixture(scope="session")
def ironcub():
    return jaxmm.load_ironcub()


def free_compiled_programs():
    """Drop the process's compiled programs. Every executable XLA's CPU backend loads keeps
    thousands of memory mappings (one compiled iRonCub solve: ≈ 12,000), and a process may hold
    65,530 (Linux's default ``vm.max_map_count``): a worker that had run several solver files
    fails to compile the next with LLVM's "Cannot allocate memory" and dies. What is needed later is loaded again from the persistent cache."""
    jax.clear_caches()
    compilation.clear_programs()
    gc.collect()


@pytest.fixture(scope="module", autouse=True)
def _free_compiled_programs():
    """Each test file's compiled programs are dropped when it ends (``free_compiled_programs``)."""
    yield
    free_compiled_programs()


REDUCED_TAKE_OFF = dict(knots=14, min_dt=0.25, max_dt=0.5)


@pytest.fixture(scope="session")
def solved_take_off():
    """The reduced take-off (14 knots of 0.25–0.5 s: the published 3.5–7 s horizon) and its
    ``solve_task`` from the published guess, shared by the files that need a solved task."""
    from jaxmm import tasks
    from jaxmm.solve import solve_task

    task = tasks.scenario("take_off", **REDUCED_TAKE_OFF)
    return task, solve_task(task)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    """A skipped test fails unless its reason names a missing accelerator (the only thing a
    machine may lack): every reference, robot and dependency the suite needs is part of the
    project or of its ``test`` and ``reference`` extras, so a skip would hide an unguarded check."""
    report = yield
    if report.skipped and not hasattr(report, "wasxfail"):
        reason = str(report.longrepr[-1]) if isinstance(report.longrepr, tuple) else str(report.longrepr)
        if "accelerator" not in reason:
            report.outcome = "failed"
            report.longrepr = f"skipped, which the suite does not allow: {reason}"
    return report


def pytest_terminal_summary(terminalreporter):
    """How many bad-input cases and fuzzing examples ran (their tests record the counts)."""
    reports = [r for key in ("passed", "failed") for r in terminalreporter.stats.get(key, []) if r.when == "call"]
    bad = [r for r in reports if "test_bad_input.py::" in r.nodeid]
    fuzz = [(r.nodeid.split("::")[-1], dict(r.user_properties)) for r in reports
            if "fuzz_examples" in dict(r.user_properties)]
    if not bad and not fuzz:
        return
    terminalreporter.write_sep("-", "bad input and fuzzing")
    if bad:
        failed = sum(r.failed for r in bad)
        terminalreporter.write_line(f"bad-input cases: {len(bad)} run, {len(bad) - failed} passed, {failed} failed")
    for name, properties in fuzz:
        statuses = f" (statuses: {properties['fuzz_statuses']})" if "fuzz_statuses" in properties else ""
        terminalreporter.write_line(f"{name}: {properties['fuzz_examples']} examples{statuses}")
