"""``tools/rounding.py``'s perturbed guesses: the guess's structure, every entry moved by a
relative amount of the order of the scale (zeros and T_total kept), the same for the same seed."""

import importlib.util
import pathlib
import sys

import jax
import numpy as np
import pytest

import jaxmm  # noqa: F401  (float64)
from jaxmm import tasks

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # rounding.py imports benchmarks/machine.py
spec = importlib.util.spec_from_file_location("rounding", ROOT / "tools" / "rounding.py")
rounding = importlib.util.module_from_spec(spec)
spec.loader.exec_module(rounding)


def test_perturbed_guess_is_a_relative_perturbation_of_the_given_scale():
    task = tasks.scenario("take_off", knots=6)
    guess = tasks.initial_guess(task)
    copy = rounding.perturbed(guess, 1e-12, seed=3)
    assert jax.tree.structure(copy) == jax.tree.structure(guess)
    assert float(copy.total_time) == float(guess.total_time)
    moved = 0
    for a, b in zip(jax.tree.leaves(guess.knots), jax.tree.leaves(copy.knots)):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.dtype == b.dtype
        assert np.all(b[a == 0] == 0)
        relative = np.abs(b - a)[a != 0] / np.abs(a[a != 0])
        assert np.all(relative < 1e-11)  # 10 standard deviations
        moved += int(np.sum(relative > 0))
    assert moved > 0.9 * sum(int(np.count_nonzero(x)) for x in jax.tree.leaves(guess.knots))
    again = rounding.perturbed(guess, 1e-12, seed=3)
    other = rounding.perturbed(guess, 1e-12, seed=4)
    assert all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(copy), jax.tree.leaves(again)))
    assert not all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(copy), jax.tree.leaves(other)))


def test_solver_options_from_the_command_line():
    options = rounding.solver_options(["regularisation_decrease=0.01", " max_iterations = 50"])
    assert options.regularisation_decrease == 0.01 and options.max_iterations == 50
    assert rounding.solver_options([]) == rounding.solve.DEFAULT_OPTIONS


@pytest.mark.parametrize("assignment, message", [("no_such_option=1", "no_such_option"), ("max_iterations", "name=value"),
                                                 ("barrier0=fast", "not a Python literal")])
def test_bad_solver_options_are_named(assignment, message):
    with pytest.raises(ValueError, match=message):
        rounding.solver_options([assignment])


def test_task_changes_from_the_command_line():
    assert rounding.task_overrides(["boundary_tolerance=0.0", "complementarity_tolerance = 1e-6"]) == dict(
        boundary_tolerance=0.0, complementarity_tolerance=1e-6)
    with pytest.raises(ValueError, match="no_such_keyword"):
        rounding.task_overrides(["no_such_keyword=1"])


def test_complementarity_of_a_trajectory():
    task = tasks.scenario("take_off", knots=6)
    guess = tasks.initial_guess(task)
    knots = guess.knots
    forces = knots.contact_forces.at[2, 1, 2].set(5.0)
    points = knots.contact_points.at[2, 1, 2].set(0.02)
    lifted = type(guess)(knots=type(knots)(**{**vars(knots), "contact_forces": forces, "contact_points": points,
                                               "tangential_slack": knots.tangential_slack.at[3, 0].set(0.25)}),
                         total_time=guess.total_time)
    assert rounding.complementarity(lifted) == pytest.approx((0.1, 0.25))
    assert rounding.complementarity(guess) == (0.0, 0.0)
