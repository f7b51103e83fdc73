"""Property-based fuzzing (hypothesis).

* Rigid-body library: random kinematic trees (2–7 links, every joint type, random axes, origins,
  masses and inertias, some links massless) at random configurations and velocities: frame
  poses, CoM and centroidal momentum equal Pinocchio's (the independent reference) to 1e-9, and
  nothing is NaN.
* Solver: random small problems (a capped double integrator with random targets, initial state,
  control box, a cap that may be infeasible, and wild or non-finite starting points): the solve
  never crashes, stops with a meaningful status (never RUNNING), returns finite numbers, a
  CONVERGED answer satisfies its constraints, and an infeasible cap is never CONVERGED.

Each test records how many examples it ran (``record_property``); the conftest prints the totals.
"""

import functools

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import HealthCheck, given, settings

import jaxmm
from jaxmm.solver import interior_point as ip

from conftest import PinocchioTwin
from test_solver import CAPPED, K, integrator

FUZZ = settings(max_examples=25, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

finite = functools.partial(st.floats, allow_nan=False, allow_infinity=False)


@st.composite
def trees(draw):
    """(URDF XML, number of links) of a random tree."""
    n = draw(st.integers(2, 7))
    links, joints = [], []
    for i in range(n):
        mass = draw(st.sampled_from([0.0, 0.5, 1.0, 3.7])) if i else 2.0  # the root keeps a mass
        principal = [draw(finite(min_value=0.01, max_value=1.0)) for _ in range(3)]
        com = " ".join(str(draw(finite(min_value=-0.3, max_value=0.3))) for _ in range(3))
        links.append(
            f'<link name="l{i}"><inertial><origin xyz="{com}" rpy="0 0 0"/><mass value="{mass}"/>'
            f'<inertia ixx="{principal[0]}" iyy="{principal[1]}" izz="{principal[2]}" ixy="0" ixz="0" iyz="0"/>'
            "</inertial></link>"
        )
        if i == 0:
            continue
        parent = draw(st.integers(0, i - 1))
        kind = draw(st.sampled_from(["revolute", "continuous", "prismatic", "fixed"]))
        axis = [draw(finite(min_value=-1, max_value=1)) for _ in range(3)]
        if np.linalg.norm(axis) < 0.1:
            axis = [0.0, 0.0, 1.0]
        xyz = " ".join(str(draw(finite(min_value=-0.5, max_value=0.5))) for _ in range(3))
        rpy = " ".join(str(draw(finite(min_value=-3.1, max_value=3.1))) for _ in range(3))
        joints.append(
            f'<joint name="j{i}" type="{kind}"><parent link="l{parent}"/><child link="l{i}"/>'
            f'<origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{" ".join(map(str, axis))}"/>'
            '<limit lower="-2" upper="2" effort="1" velocity="1"/></joint>'
        )
    return f'<robot name="fuzz">{"".join(links)}{"".join(joints)}</robot>', n


def test_random_trees_match_pinocchio(record_property):
    examples = []

    @FUZZ
    @given(tree=trees(), seed=st.integers(0, 2**31 - 1))
    def check(tree, seed):
        xml, n = tree
        robot = jaxmm.load_robot(xml)
        model = robot.model
        twin = PinocchioTwin(model, xml)
        pin = twin.pin
        rng = np.random.default_rng(seed)
        quaternion = rng.normal(size=4)
        quaternion /= np.linalg.norm(quaternion)
        q = np.concatenate([rng.uniform(-2, 2, 3), quaternion,
                            rng.uniform(np.maximum(model.position_limits[:, 0], -np.pi),
                                        np.minimum(model.position_limits[:, 1], np.pi))])
        nu = rng.normal(size=model.nv)
        positions, rotations = jaxmm.frame_poses(model, q)
        com = jaxmm.com_position(model, q)
        h = jaxmm.centroidal_momentum(model, q, nu)
        for value in (positions, rotations, com, h):
            assert np.all(np.isfinite(np.asarray(value)))
        q_pin, v_pin = twin.configuration(q), twin.velocity(q, nu)
        pin.framesForwardKinematics(twin.model, twin.data, q_pin)
        for k, name in enumerate(model.frame_names):
            placement = twin.data.oMf[twin.frame_id(name)]
            assert np.abs(placement.translation - np.asarray(positions[k])).max() <= 1e-9, name
            assert np.abs(placement.rotation - np.asarray(rotations[k])).max() <= 1e-9, name
        assert np.abs(pin.centerOfMass(twin.model, twin.data, q_pin) - np.asarray(com)).max() <= 1e-9
        assert np.abs(pin.computeCentroidalMap(twin.model, twin.data, q_pin) @ v_pin - np.asarray(h)).max() <= 1e-9
        # Inverse dynamics with a force on the last link, prismatic and massless links included.
        nu_dot, force, frame = rng.normal(size=model.nv), rng.normal(size=(1, 3)), model.frame_names[-1]
        tau = np.asarray(jaxmm.inverse_dynamics(model, q, nu, nu_dot, force, (frame,)))
        reference = twin.velocity_map(q).T @ pin.rnea(twin.model, twin.data, q_pin, v_pin, twin.acceleration(q, nu, nu_dot),
                                                      twin.external_forces(q, (frame,), force))
        assert np.abs(tau - reference).max() <= 1e-9 * max(1.0, np.abs(reference).max())
        examples.append(n)

    check()
    record_property("fuzz_examples", len(examples))
    assert len(examples) >= 10, "hypothesis ran too few examples to mean anything"


solve = jax.jit(ip.solve, static_argnames="options")
FUZZ_OPTIONS = ip.Options(max_iterations=200)
MEANINGFUL = {ip.Status.CONVERGED, ip.Status.MAX_ITERATIONS, ip.Status.STALLED, ip.Status.NAN, ip.Status.INFEASIBLE}


@st.composite
def small_problems(draw):
    a = draw(finite(min_value=-1e3, max_value=1e3))
    start = draw(finite(min_value=-1e2, max_value=1e2))
    u_max = draw(finite(min_value=1e-3, max_value=1e3))
    cap = draw(st.one_of(finite(min_value=-1.0, max_value=-1e-3), finite(min_value=1e-3, max_value=1e3)))
    scale = draw(st.sampled_from([0.0, 1.0, 1e2, 1e4]))
    poison = draw(st.sampled_from([None, np.nan, np.inf]))
    return a, start, u_max, cap, scale, poison, draw(st.integers(0, 2**31 - 1))


def test_random_small_problems_stop_with_a_meaningful_status(record_property):
    seen = []

    @FUZZ
    @given(problem=small_problems())
    def check(problem):
        a, start, u_max, cap, scale, poison, seed = problem
        nlp = integrator(CAPPED, a=a, start=start, u_max=u_max, energy_cap=cap)
        Z0 = scale * np.random.default_rng(seed).normal(size=(K, 3))
        if poison is not None:
            Z0[K // 2, 1] = poison
        solution = solve(nlp, jnp.asarray(Z0), jnp.zeros(1), FUZZ_OPTIONS)
        status = ip.Status(int(solution.status))
        assert status in MEANINGFUL, status
        finite_answer = np.all(np.isfinite(np.asarray(solution.Z))) and np.all(np.isfinite(np.asarray(solution.theta)))
        if poison is not None:
            assert status is ip.Status.NAN, status  # a non-finite start is named, never solved from
        else:
            assert finite_answer, status  # NaN only ever comes with the NAN status
        if status is ip.Status.CONVERGED:
            assert float(solution.violation) <= FUZZ_OPTIONS.tolerance
            assert np.isfinite(float(solution.objective))
        if cap < 0:
            assert status is not ip.Status.CONVERGED  # u² ≤ cap < 0 has no solution
        seen.append(status.name)

    check()
    record_property("fuzz_examples", len(seen))
    record_property("fuzz_statuses", ", ".join(f"{s} ×{seen.count(s)}" for s in sorted(set(seen))))
    assert len(seen) >= 10


def test_the_same_inputs_give_bit_identical_outputs():
    """Solving the same problem twice (same machine, same compiled program) gives the same bits
    in every output, history and multipliers included: nothing in the solve depends on timing
    or thread scheduling."""
    nlp = integrator(CAPPED, a=3.0, start=2.0, u_max=5.0, energy_cap=4.0)
    Z0 = jnp.asarray(np.random.default_rng(5).normal(size=(K, 3)))
    first, second = (solve(nlp, Z0, jnp.zeros(1), FUZZ_OPTIONS) for _ in range(2))
    assert ip.Status(int(first.status)) is ip.Status.CONVERGED
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(second)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
