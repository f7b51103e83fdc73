"""Bad input, at every public entry point, raises an error that names the problem and writes
nothing: one table per entry point (robot loading, robot selection, kinematics, task building,
solve, batch solve, save/load, command line). Every row is one test; the conftest prints how
many ran in the test summary."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmm
from jaxmm import batch, io, programs, solve, tasks
from jaxmm.cli import main

LINK = ('<link name="{name}"><inertial><mass value="{mass}"/><inertia ixx="{i}" iyy="{i}" izz="{i}" ixy="0" '
        'ixz="0" iyz="0"/></inertial></link>')
JOINT = ('<joint name="{name}" type="{type}"><parent link="{parent}"/><child link="{child}"/><axis xyz="{axis}"/>'
         '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>')


def urdf(links, joints):
    return f'<robot name="r">{"".join(links)}{"".join(joints)}</robot>'


def link(name, mass=1.0, i=0.1):
    return LINK.format(name=name, mass=mass, i=i)


def joint(name, parent, child, type="revolute", axis="0 0 1"):
    return JOINT.format(name=name, parent=parent, child=child, type=type, axis=axis)


GOOD = urdf([link("base"), link("a"), link("b")], [joint("j1", "base", "a"), joint("j2", "a", "b")])

# ------------------------------------------------------------------------------ robot loading

URDF_CASES = {
    "missing file": ("/no/such/robot.urdf", FileNotFoundError, "/no/such/robot.urdf"),
    "malformed XML": ("<robot name='r'><link name='a'></robot>", jaxmm.URDFError, "could not parse"),
    "empty robot": ("<robot name='r'></robot>", jaxmm.URDFError, "no links"),
    "two roots": (urdf([link("base"), link("a"), link("b")], [joint("j1", "base", "a")]), jaxmm.URDFError,
                  "exactly one root"),
    "a loop": (urdf([link("a"), link("b")], [joint("j1", "a", "b"), joint("j2", "b", "a")]), jaxmm.URDFError,
               "a loop"),
    "child of two joints": (urdf([link("base"), link("a"), link("b")],
                                 [joint("j1", "base", "a"), joint("j2", "base", "b"), joint("j3", "b", "a")]),
                            jaxmm.URDFError, "child of two joints"),
    "negative mass": (urdf([link("base"), link("a", mass=-1)], [joint("j1", "base", "a")]), jaxmm.URDFError,
                      "invalid mass"),
    "NaN mass": (urdf([link("base"), link("a", mass="nan")], [joint("j1", "base", "a")]), jaxmm.URDFError,
                 "invalid mass"),
    "no mass at all": (urdf([link("base", mass=0), link("a", mass=0)], [joint("j1", "base", "a")]), jaxmm.URDFError,
                       "no mass"),
    "inertia not positive semi-definite": (urdf([link("base"), link("a", i=-0.1)], [joint("j1", "base", "a")]),
                                           jaxmm.URDFError, "not positive semi-definite"),
    "infinite inertia": (urdf([link("base"), link("a", i="inf")], [joint("j1", "base", "a")]), jaxmm.URDFError,
                         "non-finite inertia"),
    "duplicated link names": (urdf([link("base"), link("a"), link("a")], [joint("j1", "base", "a")]),
                              jaxmm.URDFError, "duplicated link names: a"),
    "duplicated joint names": (urdf([link("base"), link("a"), link("b")], [joint("j", "base", "a"),
                                                                          joint("j", "a", "b")]),
                               jaxmm.URDFError, "duplicated joint names: j"),
    "unknown link": (urdf([link("base"), link("a")], [joint("j1", "base", "ghost")]), jaxmm.URDFError,
                     "unknown link 'ghost'"),
    "unsupported joint type": (urdf([link("base"), link("a")], [joint("j1", "base", "a", type="planar")]),
                               jaxmm.URDFError, "unsupported type"),
    "zero joint axis": (urdf([link("base"), link("a")], [joint("j1", "base", "a", axis="0 0 0")]), jaxmm.URDFError,
                        "zero axis"),
    "not a URDF at all": (42, TypeError, "expected a URDF path"),
}


@pytest.mark.parametrize("source, error, message", URDF_CASES.values(), ids=URDF_CASES.keys())
def test_bad_urdf(source, error, message):
    with pytest.raises(error, match=message.replace("(", r"\(")):
        jaxmm.load_robot(source)


def test_good_urdf_loads():
    robot = jaxmm.load_robot(GOOD)
    assert robot.model.joint_names == ("j1", "j2")
    assert float(jaxmm.total_mass(robot.model)) == 3.0


SELECTION_CASES = {
    "unknown joint": (dict(joints=["j1", "j3"]), jaxmm.UnknownNameError, "unknown joint 'j3'; did you mean 'j2', 'j1'"),
    "unknown locked joint": (dict(joints=["j1"], locked={"j9": 0.0}), jaxmm.UnknownNameError, "unknown joint 'j9'"),
    "joint optimised and locked": (dict(joints=["j1"], locked={"j1": 0.0}), ValueError, "both optimised and locked"),
    "joint listed twice": (dict(joints=["j1", "j1"]), ValueError, "more than once"),
    "unknown jet frame": (dict(jet_frames=["nozzle"]), jaxmm.UnknownNameError, "unknown frame 'nozzle'"),
    "unknown contact frame": (dict(contact_frames=["toe"]), jaxmm.UnknownNameError, "unknown frame 'toe'"),
    "standing configuration of the wrong shape": (dict(standing_configuration=np.zeros(5)), ValueError,
                                                  r"shape \(9,\)"),
    "standing configuration with a zero quaternion": (dict(standing_configuration=np.zeros(9)), ValueError,
                                                      "has norm 0, not 1"),
}


@pytest.mark.parametrize("kwargs, error, message", SELECTION_CASES.values(), ids=SELECTION_CASES.keys())
def test_bad_selection(kwargs, error, message):
    with pytest.raises(error, match=message):
        jaxmm.load_robot(GOOD, **kwargs)


def test_fixed_joint_cannot_be_optimised():
    fixed = urdf([link("base"), link("a"), link("b")], [joint("j1", "base", "a"), joint("f", "a", "b", type="fixed")])
    with pytest.raises(ValueError, match="joint 'f' is fixed"):
        jaxmm.load_robot(fixed, joints=["f"])


# ------------------------------------------------------------------------------- kinematics


@functools.cache
def ironcub():
    return jaxmm.load_ironcub()


def _q(**changes):
    q = np.array(ironcub().standing_configuration)
    for index, value in changes.items():
        q[int(index[1:])] = value
    return q


KINEMATICS_CASES = {
    "unknown frame": (lambda m: jaxmm.frame_pose(m, _q(), "l_sole_9"), jaxmm.UnknownNameError,
                      "unknown frame 'l_sole_9'; did you mean 'l_sole_"),
    "frame index out of range": (lambda m: jaxmm.frame_pose(m, _q(), 10000), IndexError,
                                 "frame index 10000 out of range"),
    "configuration too short": (lambda m: jaxmm.com_position(m, _q()[:-1]), ValueError,
                                r"configuration q must have shape \(30,\).*got \(29,\)"),
    "a batch where one q is expected": (lambda m: jaxmm.centroidal_momentum_matrix(m, np.stack([_q(), _q()])),
                                        ValueError, r"got \(2, 30\)"),
    "complex configuration": (lambda m: jaxmm.com_position(m, _q().astype(complex)), TypeError, "dtype complex128"),
    "NaN in a joint angle": (lambda m: jaxmm.com_position(m, _q(i12=np.nan)), ValueError,
                             r"non-finite entries at indices \[12\]"),
    "non-unit quaternion": (lambda m: jaxmm.frame_pose(m, _q(i6=2.0), "l_sole"), ValueError, r"has norm 2\.0000\d, not 1"),
    "velocity of the wrong size": (lambda m: jaxmm.centroidal_momentum(m, _q(), np.zeros(30)), ValueError,
                                   r"velocity ν must have shape \(29,\)"),
    "unknown joint name": (lambda m: m.joint_index("neck_pitch"), jaxmm.UnknownNameError,
                           "unknown optimised joint 'neck_pitch'"),
    "a frame name that is not a string": (lambda m: m.frame_index(3.5), TypeError, "name must be a string"),
}


@pytest.mark.parametrize("call, error, message", KINEMATICS_CASES.values(), ids=KINEMATICS_CASES.keys())
def test_bad_kinematics_input(call, error, message):
    with pytest.raises(error, match=message):
        call(ironcub().model)


def test_a_traced_configuration_is_not_checked_by_value():
    """Under jit the values are unknown when tracing: a non-unit quaternion is normalised by the
    kinematics instead (the by-value check is for eager calls)."""
    model = ironcub().model
    q = _q()
    q_scaled = q.copy()
    q_scaled[3:7] *= 2.0
    np.testing.assert_allclose(jax.jit(jaxmm.com_position)(model, q_scaled),
                               jaxmm.com_position(model, q), atol=1e-14)


# ---------------------------------------------------------------------------- task building

def _take_off(knots=14, **overrides):
    return tasks.scenario("take_off", knots=knots, keep_horizon=True, **overrides)


def _build(**overrides):
    arguments = dict(robot=ironcub(), initial_com=(0.0, 0.0, 0.55), final_com=(0.0, 0.0, 0.8), knots=10,
                     weights={}, jet_coefficients=np.zeros((4, 10)), max_thrust=np.full(4, 160.0))
    arguments.update(overrides)
    return tasks.build_task(**arguments)


TASK_CASES = {
    "unknown scenario": (lambda: tasks.scenario("hover"), ValueError, "unknown scenario 'hover'"),
    "knot count 0": (lambda: tasks.scenario("take_off", knots=0), ValueError, "knots must be an integer N ≥ 2"),
    "knot count 1": (lambda: tasks.scenario("take_off", knots=1), ValueError, "knots must be an integer N ≥ 2"),
    "fractional knot count": (lambda: tasks.scenario("take_off", knots=10.5), ValueError,
                              "knots must be an integer N ≥ 2"),
    "negative time step": (lambda: _take_off(min_dt=-0.1), ValueError, "0 < min_dt ≤ max_dt"),
    "time-step bounds crossed": (lambda: _build(min_dt=0.2, max_dt=0.1), ValueError, "0 < min_dt ≤ max_dt"),
    "infinite time step": (lambda: _build(max_dt=np.inf), ValueError, "0 < min_dt ≤ max_dt < ∞"),
    "target outside the workspace": (lambda: _take_off(final_com=(9.0, 0.0, 0.8)), ValueError,
                                     "outside the workspace"),
    "target below the ground": (lambda: _take_off(final_com=(0.0, 0.0, -0.5)), ValueError, "outside the workspace"),
    "NaN target": (lambda: _take_off(final_com=(0.0, np.nan, 0.8)), ValueError, "final_com must be finite"),
    "target of the wrong shape": (lambda: _take_off(final_com=(0.0, 0.8)), ValueError,
                                  r"final_com must have shape \(3,\)"),
    "jets without coefficients": (lambda: _build(jet_coefficients=None), ValueError,
                                  "has 4 jets: jet_coefficients .* are required"),
    "jet coefficients of the wrong shape": (lambda: _build(jet_coefficients=np.zeros((4, 9))), ValueError,
                                            r"jet_coefficients must have shape \(4, 10\)"),
    "infinite maximum thrust": (lambda: _build(max_thrust=np.full(4, np.inf)), ValueError,
                                "max_thrust must be finite"),
    "unknown weight": (lambda: _take_off(weights={"thrus": 1.0}), ValueError, r"unknown cost weights \['thrus'\]"),
    "negative weight": (lambda: _build(weights={"thrust": -1.0}), ValueError,
                        "weight 'thrust' must be finite and non-negative"),
    "NaN weight": (lambda: _build(weights={"thrust": np.nan}), ValueError, "must be finite and non-negative"),
    "negative friction": (lambda: _take_off(friction_coefficient=-0.3), ValueError,
                          "friction_coefficient must be a finite positive number"),
    "NaN mid-horizon height": (lambda: _build(mid_com_height=np.nan), ValueError, "mid_com_height must be finite"),
    "throttle range reversed": (lambda: _build(throttle_range=(100.0, 0.0)), ValueError, "lower ≤ upper"),
    "joint limits of the wrong shape": (lambda: _build(joint_limits=np.zeros((3, 2))), ValueError,
                                        r"joint_limits must have shape \(23, 2\)"),
    "unknown integration rule": (lambda: _build(integration="rk4"), ValueError, "integration must be one of"),
    "unknown upper-body joint": (lambda: _build(upper_body_joints=("torso_yawn",)), jaxmm.UnknownNameError,
                                 "unknown optimised joint 'torso_yawn'"),
}


@pytest.mark.parametrize("call, error, message", TASK_CASES.values(), ids=TASK_CASES.keys())
def test_bad_task(call, error, message):
    with pytest.raises(error, match=message):
        call()


# ------------------------------------------------------------------------ solve, batch solve

@functools.cache
def take_off():
    return _take_off()


def _guess(**changes):
    """The published guess with its knot fields replaced: {field: function of the array}."""
    guess = tasks.initial_guess(take_off())
    return dataclasses.replace(guess, knots=dataclasses.replace(
        guess.knots, **{name: change(getattr(guess.knots, name)) for name, change in changes.items()}))


SOLVE_CASES = {
    "task is not a Task": (lambda: solve.solve_task("take_off"), TypeError, "task must be a Task"),
    "guess is not a Trajectory": (lambda: solve.solve_task(take_off(), guess=np.zeros(10)), TypeError,
                                  "guess must be a Trajectory"),
    "guess with too few knots": (lambda: solve.solve_task(take_off(), guess=tasks.initial_guess(_take_off(
        knots=10))), ValueError, r"has shape \(11, 3\); the task \(15 knots\) needs \(15, 3\)"),
    "NaN in the guess": (lambda: solve.solve_task(take_off(), guess=_guess(thrust=lambda t: t.at[3, 1].set(
        np.nan))), ValueError, r"guess.*thrust has non-finite entries"),
    "infinite total time": (lambda: solve.solve_task(take_off(), guess=dataclasses.replace(
        tasks.initial_guess(take_off()), total_time=jnp.inf)), ValueError, "total_time has non-finite entries"),
    "complex guess": (lambda: solve.solve_task(take_off(), guess=_guess(com=lambda c: c.astype(complex))),
                      TypeError, "dtype complex128"),
    "warm start is not a solution": (lambda: solve.solve_task(take_off(), warm_start=tasks.initial_guess(
        take_off())), TypeError, "warm_start must be a TaskSolution"),
    "options of the wrong kind": (lambda: solve.solve_task(take_off(), options={"max_iterations": 3}), TypeError,
                                  "options must be interior_point.Options"),
    "time budget of zero": (lambda: solve.solve_task(take_off(), time_budget=0), ValueError,
                            "time_budget must be a positive number of seconds, got 0"),
    "time budget that is not a number": (lambda: programs.compile_solve(take_off(), time_budget="60"), ValueError,
                                         "time_budget must be a positive number of seconds, got '60'"),
    "batch of guesses with one scalar time": (lambda: batch.solve_batch(take_off(), tasks.initial_guess(take_off())),
                                              ValueError, "must have a leading batch axis"),
    "batch mesh that is not a Mesh": (lambda: batch.solve_batch(take_off(), [tasks.initial_guess(take_off())] * 2,
                                                            mesh="cpu"), TypeError, "mesh must be a one-axis Mesh"),
    "batch of an empty list": (lambda: batch.solve_batch(take_off(), []), ValueError, r"cannot stack an empty list \(no guess given\)"),
    "batch with a NaN guess": (lambda: batch.solve_batch(take_off(), [tasks.initial_guess(take_off()), _guess(
        contact_points=lambda p: p.at[0, 0, 0].set(np.inf))]), ValueError, r"guesses.*contact_points has non-finite"),
    "batch of tasks of two knot counts": (lambda: batch.stack_tasks([take_off(), _take_off(knots=10)]), ValueError,
                                          "task 1 cannot be batched with task 0.*n_intervals: 14 vs 10"),
    "batch with a guess per task missing": (lambda: batch.solve_batch(
        [take_off(), take_off()], batch.stack_trajectories([tasks.initial_guess(take_off())] * 3)), ValueError,
        "3 guesses for a batch of 2 tasks"),
    "negative number of sampled guesses": (lambda: batch.sample_guesses(take_off(), jax.random.key(0), -1),
                                           ValueError, "n must be a positive integer"),
    "sampler given an integer seed": (lambda: batch.sample_guesses(take_off(), 0, 4), TypeError,
                                      "key must be one JAX PRNG key"),
    "elastic continuation that lowers the weight": (lambda: solve.solve_elastic(take_off(), factor=0.5), ValueError,
                                                    "factor > 1"),
    "elastic continuation to a zero tolerance": (lambda: solve.solve_elastic(take_off(), tolerance=0.0), ValueError,
                                                 "tolerance > 0"),
    "smooth start of no iterations": (lambda: solve.solve_elastic(take_off(), smooth_start=True, smooth_iterations=0),
                                      ValueError, "smooth_iterations > 0"),
}


@pytest.mark.parametrize("call, error, message", SOLVE_CASES.values(), ids=SOLVE_CASES.keys())
def test_bad_solve_input(call, error, message):
    with pytest.raises(error, match=message):
        call()


# ------------------------------------------------------------------------------- save, load

def _unsolved():
    """A TaskSolution-shaped value built without solving (the published guess as the answer)."""
    return solve.TaskSolution(tasks.initial_guess(take_off()), None, {})


SAVE_CASES = {
    "save a guess instead of a solution": (lambda d: io.save(d / "s.npz", take_off(), tasks.initial_guess(
        take_off())), TypeError, "needs a Task and a TaskSolution"),
    "save a solution of another knot count": (lambda d: io.save(d / "s", _take_off(knots=10), _unsolved()),
                                              ValueError, "the result has 15 knots, the task 11"),
    "save into a missing directory": (lambda d: io.save(d / "no" / "s.npz", take_off(), _unsolved()),
                                      FileNotFoundError, "does not exist"),
}


def _tree(directory):
    """Every path under directory (hidden temporaries and subdirectories included)."""
    return sorted(p.relative_to(directory) for p in directory.rglob("*"))


@pytest.mark.parametrize("call, error, message", SAVE_CASES.values(), ids=SAVE_CASES.keys())
def test_bad_save_input(call, error, message, tmp_path):
    """A refused save leaves the directory as it was: no file under the name asked for, none
    under it with the ``.npz`` numpy's savez appends, no temporary, no directory."""
    before = _tree(tmp_path)
    with pytest.raises(error, match=message):
        call(tmp_path)
    assert _tree(tmp_path) == before


LOAD_CASES = {
    "load a missing file": ("missing.npz", lambda path: None, FileNotFoundError, "no solution file"),
    "load a text file": ("t.npz", lambda path: path.write_bytes(b"hello"), io.SolutionFileError,
                         "not a readable .npz solution file"),
    "load an npz without a header": ("h.npz", lambda path: np.savez(path, x=np.zeros(3)), io.SolutionFileError,
                                     "no jaxmm header"),
    "load a header that is not JSON": ("j.npz", lambda path: np.savez(path, **{io.HEADER: np.array("{")}),
                                       io.SolutionFileError, "corrupt header"),
}


@pytest.mark.parametrize("name, write, error, message", LOAD_CASES.values(), ids=LOAD_CASES.keys())
def test_bad_load_input(name, write, error, message, tmp_path):
    """A refused file is left as it was, and nothing is written beside it."""
    write(tmp_path / name)
    before = {path: (tmp_path / path).read_bytes() for path in _tree(tmp_path)}
    with pytest.raises(error, match=message):
        io.load(tmp_path / name)
    assert {path: (tmp_path / path).read_bytes() for path in _tree(tmp_path)} == before


# ------------------------------------------------------------------------------ command line

CLI_CASES = {
    "unknown scenario": (["solve", "hover"], "unknown scenario 'hover'"),
    "target outside the workspace": (["solve", "take-off", "--target", "9", "0", "0.8"], "outside the workspace"),
    "target below the ground": (["solve", "take-off", "--target", "0", "0", "-1"], "outside the workspace"),
    "NaN target": (["solve", "take-off", "--target", "nan", "0", "0.8"], "final_com must be finite"),
    "missing URDF": (["solve", "take-off", "--urdf", "/no/such.urdf"], "URDF file not found: /no/such.urdf"),
    "URDF without iRonCub's frames": (["solve", "take-off", "--urdf", "{good}"], "unknown"),
    "compare an unknown scenario": (["compare", "hover"], "unknown scenario 'hover'"),
    "robot summary of a malformed URDF": (["robot", "--urdf", "{bad}"], "could not parse"),
}


@pytest.mark.parametrize("argv, message", CLI_CASES.values(), ids=CLI_CASES.keys())
def test_bad_command_line(argv, message, tmp_path, capsys):
    (tmp_path / "good.urdf").write_text(GOOD)
    (tmp_path / "bad.urdf").write_text("<robot")
    argv = [a.format(good=tmp_path / "good.urdf", bad=tmp_path / "bad.urdf") for a in argv]
    out = tmp_path / "out"
    if argv[0] == "solve":
        argv += ["--out", str(out)]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("argv", [["solve", "take-off", "--knots", "1"], ["solve"], ["fly"],
                                  ["solve", "take-off", "--target", "1", "2"],
                                  ["solve", "take-off", "--time-budget", "-5"], ["solve", "take-off", "--time-budget", "inf"]],
                         ids=["one knot", "no scenario", "unknown command", "target of two numbers", "negative time budget",
                              "infinite time budget"])
def test_command_line_usage_errors_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as exit:
        main(argv)
    assert exit.value.code == 2 and "usage: jaxmm" in capsys.readouterr().err

