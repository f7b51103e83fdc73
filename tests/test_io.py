"""Saved solutions: a round trip keeps every number and the structure; foreign, corrupt and
mismatched files are refused with a clear error; a failed save loses nothing."""

import dataclasses
import json
import os

import jax
import numpy as np
import pytest

from jaxmm import io, tasks


@pytest.fixture(scope="module")
def saved(solved_take_off, tmp_path_factory):
    task, result = solved_take_off
    path = tmp_path_factory.mktemp("saved") / "take_off.npz"
    assert io.save(path, task, result) == os.fspath(path)
    return path, task, result


def _leaves_equal(a, b):
    paths_a, tree_a = jax.tree_util.tree_flatten_with_path(a)
    paths_b, tree_b = jax.tree_util.tree_flatten_with_path(b)
    assert tree_a == tree_b
    for (path, x), (_, y) in zip(paths_a, paths_b):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape, jax.tree_util.keystr(path)
        np.testing.assert_array_equal(x, y, err_msg=jax.tree_util.keystr(path))


def test_round_trip_keeps_every_number_and_the_structure(saved):
    path, task, result = saved
    loaded_task, loaded = io.load(path)
    _leaves_equal(loaded.trajectory, result.trajectory)
    _leaves_equal(loaded.solution, result.solution)  # multipliers and bound multipliers: a warm start
    _leaves_equal(loaded_task.params, task.params)
    _leaves_equal(loaded_task.weights, task.weights)
    assert jax.tree_util.tree_structure(loaded_task) == jax.tree_util.tree_structure(task)  # same compiled solve
    assert loaded.status == result.status
    assert loaded.violation_per_family.keys() == result.violation_per_family.keys()


def test_the_header_is_readable_without_jax(saved):
    path, task, result = saved
    header = io.read_header(path)
    assert header["format"] == io.FORMAT and header["version"] == io.VERSION
    assert header["status"]["name"] == result.status.name
    assert header["task"]["name"] == "take_off" and header["task"]["n_intervals"] == task.n_intervals
    assert header["objective"] == float(result.solution.objective)
    assert header["robot"]["fingerprint"] == io.robot_fingerprint(task.robot)
    with np.load(path, allow_pickle=False) as data:  # plain arrays only: no pickles
        assert "trajectory.knots.com" in data.files


@pytest.mark.parametrize("version, missing", [(1, 3), (2, 2), (3, 1)])
def test_an_older_file_is_read_with_its_history_missing_the_newer_columns(saved, tmp_path, version, missing):
    """Files written before the history had its linear-solves (version 1), restoration
    (version 2) and factorisations (version 3) columns still load (and plot), those columns NaN."""
    path, _, result = saved

    def as_older(arrays):
        arrays["solution.history"] = arrays["solution.history"][:, :-missing]
        content = json.loads(str(arrays["__header__"]))
        arrays["__header__"] = np.array(json.dumps({**content, "version": version}))

    _, loaded = io.load(_rewrite(path, tmp_path / f"version_{version}.npz", as_older))
    history, original = np.asarray(loaded.solution.history), np.asarray(result.solution.history)
    assert history.shape == original.shape
    np.testing.assert_array_equal(history[:, :-missing], original[:, :-missing])
    assert np.all(np.isnan(history[:, -missing:]))
    _leaves_equal(loaded.trajectory, result.trajectory)


def test_a_file_before_version_5_solved_the_published_complementarity(saved, tmp_path):
    """Files written before the complementarity's σ and slack bound were task parameters load with
    the published relaxation's values (σ = 0, ε_max = ∞), which is what they solved."""
    path, task, _ = saved

    def as_version_4(arrays):
        content = json.loads(str(arrays["__header__"]))
        fields = content["task"]["params"]["fields"]
        for name in ("complementarity_tolerance", "slack_limit"):
            del arrays[fields.pop(name)["array"]]
        arrays["__header__"] = np.array(json.dumps({**content, "version": 4}))

    loaded, _ = io.load(_rewrite(path, tmp_path / "version_4.npz", as_version_4))
    assert float(loaded.params.complementarity_tolerance) == 0.0 and float(loaded.params.slack_limit) == np.inf
    _leaves_equal(loaded.params, task.params)


def _without_param(saved_task, result, tmp_path, name, version):
    """``saved_task`` with ``result`` saved, then rewritten as a file of ``version`` that lacks
    the task parameter ``name``, and loaded: the loaded task."""
    io.save(tmp_path / "new.npz", saved_task, result)

    def as_older(arrays):
        content = json.loads(str(arrays["__header__"]))
        del arrays[content["task"]["params"]["fields"].pop(name)["array"]]
        arrays["__header__"] = np.array(json.dumps({**content, "version": version}))

    return io.load(_rewrite(tmp_path / "new.npz", tmp_path / f"version_{version}.npz", as_older))[0]


def test_a_file_before_version_7_bounds_the_planar_rows_by_its_normal_sigma(saved, tmp_path):
    """Files written while one σ bounded both complementarity rows (eq. 20, 21) load with the
    planar rows' σ_t equal to that σ, which is what they solved."""
    _, task, result = saved
    exact = tasks.exact_complementarity(task, 2e-6, None)
    loaded = _without_param(exact, result, tmp_path, "planar_tolerance", 6)
    assert float(loaded.params.planar_tolerance) == 2e-6
    _leaves_equal(loaded.params, exact.params)


def test_a_file_before_version_8_widened_both_complementarity_rows_alike(saved, tmp_path):
    """Files written before the relaxation homotopy's share on the planar rows was a task
    parameter load with ``planar_relaxation`` = 1, which is what they solved."""
    _, task, result = saved
    shared = dataclasses.replace(task, params=dataclasses.replace(task.params, planar_relaxation=jax.numpy.asarray(0.1)))
    loaded = _without_param(shared, result, tmp_path, "planar_relaxation", 7)
    assert float(loaded.params.planar_relaxation) == 1.0
    _leaves_equal(loaded.params, task.params)


@pytest.mark.parametrize("penalty", ["linear", "squared"])
def test_a_file_before_version_6_keeps_its_slack_penalty(saved, tmp_path, penalty):
    """Files written while the slack penalty was a static option (the task's ``slack_penalty``,
    one slack weight) load with that weight on the penalty they named, the other one zero."""
    path, task, _ = saved

    def as_version_5(arrays):
        content = json.loads(str(arrays["__header__"]))
        del arrays[content["task"]["weights"]["fields"].pop("complementarity_slack_squared")["array"]]  # 0.0
        content["task"]["slack_penalty"] = penalty
        arrays["__header__"] = np.array(json.dumps({**content, "version": 5}))

    loaded, _ = io.load(_rewrite(path, tmp_path / "version_5.npz", as_version_5))
    weight = float(task.weights.complementarity_slack)
    expected = (weight, 0.0) if penalty == "linear" else (0.0, weight)
    weights = loaded.weights
    assert (float(weights.complementarity_slack), float(weights.complementarity_slack_squared)) == expected
    assert jax.tree_util.tree_structure(loaded) == jax.tree_util.tree_structure(task)


def test_a_file_from_another_robot_is_refused(saved, ironcub):
    path, _, _ = saved
    without_jets = dataclasses.replace(ironcub, jet_frames=())
    with pytest.raises(io.SolutionFileError, match="another robot: jet_frames"):
        io.load(path, robot=without_jets)
    heavier = dataclasses.replace(
        ironcub, model=dataclasses.replace(ironcub.model, inertial_mass=ironcub.model.inertial_mass.at[0].add(1.0))
    )
    with pytest.raises(io.SolutionFileError, match="another robot: mass"):
        io.load(path, robot=heavier)


def _rewrite(source, target, change):
    with np.load(source, allow_pickle=False) as data:
        arrays = {key: data[key] for key in data.files}
    change(arrays)
    np.savez(target, **arrays)
    return target


def test_corrupt_and_foreign_files_are_refused(saved, tmp_path):
    path, _, _ = saved
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(path.read_bytes()[:1000])
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file at all")
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, x=np.zeros(3))

    def header(arrays, **changes):
        content = json.loads(str(arrays["__header__"]))
        content.update(changes)
        arrays["__header__"] = np.array(json.dumps(content))

    cases = {
        truncated: "not a readable .npz",
        garbage: "not a readable .npz",
        foreign: "no jaxmm header",
        _rewrite(path, tmp_path / "format.npz", lambda a: header(a, format="other")): "not a jaxmm solution",
        _rewrite(path, tmp_path / "version.npz", lambda a: header(a, version=99)): "format version 99",
        _rewrite(path, tmp_path / "missing.npz", lambda a: a.pop("trajectory.knots.com")): "'trajectory.knots.com' is missing",
        _rewrite(path, tmp_path / "header.npz", lambda a: a.update(__header__=np.array("{oops"))): "corrupt header",
    }
    for file, message in cases.items():
        with pytest.raises(io.SolutionFileError, match=message):
            io.load(file)
    with pytest.raises(FileNotFoundError, match="no solution file"):
        io.load(tmp_path / "absent.npz")


def test_a_failed_save_leaves_the_previous_file_and_no_temporary(saved, tmp_path, monkeypatch):
    path, task, result = saved
    target = tmp_path / "solution.npz"
    target.write_bytes(path.read_bytes())
    before = target.read_bytes()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", interrupted)
    with pytest.raises(KeyboardInterrupt):
        io.save(target, task, result)
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["solution.npz"]


def test_save_argument_errors(saved, tmp_path):
    _, task, result = saved
    with pytest.raises(FileNotFoundError, match="does not exist"):
        io.save(tmp_path / "no" / "such" / "dir.npz", task, result)
    with pytest.raises(TypeError, match="needs a Task and a TaskSolution"):
        io.save(tmp_path / "x.npz", result, task)
    assert not list(tmp_path.iterdir())


def test_the_joint_torque_option_round_trips_and_older_files_have_it_off(saved, tmp_path):
    """``Task.joint_torque_limits`` is saved and loaded; a file written before the option existed
    solved the paper's NLP, without it."""
    path, task, result = saved
    bounded = dataclasses.replace(task, joint_torque_limits=True)
    loaded, _ = io.load(io.save(tmp_path / "bounded.npz", bounded, result))
    assert loaded.joint_torque_limits and not io.load(path)[0].joint_torque_limits

    def without_the_option(arrays):
        content = json.loads(str(arrays["__header__"]))
        del content["task"]["joint_torque_limits"]
        arrays["__header__"] = np.array(json.dumps(content))

    older, _ = io.load(_rewrite(tmp_path / "bounded.npz", tmp_path / "older.npz", without_the_option))
    assert older.joint_torque_limits is False
