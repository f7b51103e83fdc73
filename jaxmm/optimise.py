"""Solve a task: the task's stage-wise NLP handed to the interior-point solver, and the answer
brought back as a trajectory in physical units.

This is the public boundary where compilation happens: ``solve_task`` jit-compiles one solve per
problem structure (robot, knot count, integration rule, options) and reuses it for every task of
that structure, whatever its numbers (targets, weights, bounds).
"""

import dataclasses
import functools

import jax

from jaxmm.solver import interior_point as ip
from jaxmm.tasks import initial_guess
from jaxmm.transcription import nlp as transcription
from jaxmm.transcription.variables import Trajectory


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TaskSolution:
    """A solved task: the optimal ``trajectory`` (physical units) and the solver's ``solution``
    (scaled variables, multipliers, status, statistics, history; see ``ip.Solution``)."""

    trajectory: Trajectory
    solution: ip.Solution

    @property
    def status(self):
        return ip.Status(int(self.solution.status))


DEFAULT_OPTIONS = ip.Options()


@functools.partial(jax.jit, static_argnames="options")
def _solve(task, guess, options, multipliers):
    nlp = transcription.stagewise_nlp(task)
    Z0, theta0 = transcription.to_variables(task, guess)
    solution = ip.solve(nlp, Z0, theta0, options, multipliers)
    return TaskSolution(transcription.to_trajectory(task, solution.Z, solution.theta), solution)


def solve_task(task, guess=None, options=DEFAULT_OPTIONS, multipliers=None):
    """Optimise ``task`` (a ``Task``) from ``guess`` (a ``Trajectory``; default: the published
    initial guess), warm-started with ``multipliers`` (from a previous ``TaskSolution``) if
    given. Returns a ``TaskSolution``; check ``.status`` and ``jaxmm.analysis.validate``.

    The default tolerance (scaled violation ≤ 1e-6) is tighter than the paper's IPOPT setting
    (1e-4 in physical units).
    """
    guess = initial_guess(task) if guess is None else guess
    return _solve(task, guess, options, multipliers)
