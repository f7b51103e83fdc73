"""Cost-weight tuning by gradient descent through optimal trajectories.

The paper hand-tuned 10–15 weights of eq. (32) per scenario. ``tune_weights`` tunes chosen
weights instead by minimising a loss of the optimal trajectory with an optax optimiser: each
step solves the task (warm-started from the previous step's solution) and differentiates the
optimum with respect to the weights by implicit differentiation at that solution
(``jaxmm.solve.gradient``: one adjoint solve, no differentiation through the solver).
Log-weights keep every weight positive and make the steps relative.
"""

import dataclasses
from typing import Callable

import jax.numpy as jnp
import numpy as np
import optax

from jaxmm.solve import DEFAULT_OPTIONS, gradient, solve_task
from jaxmm.solver import interior_point as ip


@dataclasses.dataclass(frozen=True)
class TuningResult:
    """Outcome of ``tune_weights``.

    names: the tuned weights' names; weights: the final ``Weights`` (those with the lowest loss
    seen); loss: (S,) loss at every step (S ≤ steps); log_weights: (S, n) the log-weights at
    which it was evaluated; gradients: (S, n) d loss / d log-weights there; status: (S,) the
    solver's status codes; iterations: (S,) its iterations; stopped: why tuning ended;
    solution: the ``TaskSolution`` at the final weights.
    """

    names: tuple
    weights: object
    loss: np.ndarray
    log_weights: np.ndarray
    gradients: np.ndarray
    status: np.ndarray
    iterations: np.ndarray
    stopped: str
    solution: object

    def __str__(self):
        lines = [f"weight tuning: {len(self.loss)} steps, {self.stopped}",
                 f"{'step':>4} {'loss':>12} {'it.':>5}  " + "  ".join(f"{n:>14}" for n in self.names)]
        for k, (value, logs, it) in enumerate(zip(self.loss, self.log_weights, self.iterations)):
            lines.append(f"{k:4d} {value:12.6g} {int(it):5d}  " + "  ".join(f"{np.exp(v):14.6g}" for v in logs))
        return "\n".join(lines)


def _with_weights(task, names, log_weights):
    values = {name: jnp.exp(log_weights[i]) for i, name in enumerate(names)}
    return dataclasses.replace(task, weights=dataclasses.replace(task.weights, **values))


def tune_weights(task, loss: Callable, names=None, optimizer=None, steps=20, options=DEFAULT_OPTIONS,
                 guess=None, warm_start=None, tolerance=0.0, callback=None, max_residual=1e-5):
    """Minimise ``loss(task, trajectory)`` (a differentiable scalar of the optimal
    ``Trajectory``) over the log of the cost weights ``names`` of ``task``.

    names: ``Weights`` field names (default: every weight that is nonzero in ``task``; a zero
    weight cannot be tuned in log space); optimizer: an optax ``GradientTransformation``
    (default ``optax.adam(0.1)``: 10 % relative weight changes per step); steps: optimiser
    steps at most; options: solver ``interior_point.Options``; guess: the first solve's guess
    (default: the published one); warm_start: a ``TaskSolution`` to warm-start the first solve
    from instead (say, the solution at the starting weights); later solves warm-start from the
    previous one;
    tolerance: stop once the loss is at or below it; callback(step, loss, weights_dict) is
    called after every evaluation; max_residual: the largest relative residual of the adjoint
    KKT solve (``Diagnostics.residual``) whose gradient is used: a descent step needs the
    gradient's direction, not the 1e-8 that ``Diagnostics.reliable`` asks by default (near a
    change of contact schedule GMRES stalls at 1e-7–1e-5 within its cycles). Stops early, and says why in ``stopped``, when a solve does
    not converge or the gradient is not finite. Returns a ``TuningResult``.
    """
    fields = {f.name for f in dataclasses.fields(task.weights)}
    if names is None:
        names = tuple(n for n in sorted(fields) if float(getattr(task.weights, n)) > 0.0)
    names = tuple(names)
    unknown = [n for n in names if n not in fields]
    if unknown:
        raise ValueError(f"unknown weight name(s) {unknown}; the weights are {sorted(fields)}")
    nonpositive = [n for n in names if not float(getattr(task.weights, n)) > 0.0]
    if nonpositive:
        raise ValueError(f"weight(s) {nonpositive} are not positive: log-space tuning needs a positive start")
    if not names:
        raise ValueError("no weight to tune")
    optimizer = optax.adam(0.1) if optimizer is None else optimizer

    def evaluate(log_weights, previous):
        """(loss, d loss / d log-weights, the solve, the adjoint's diagnostics)."""
        tuned = _with_weights(task, names, log_weights)
        result = solve_task(tuned, guess if previous is None else None, options, warm_start=previous)
        value, task_bar, diagnostics = gradient(tuned, result, loss)
        weights = np.asarray([float(getattr(tuned.weights, n)) for n in names])
        d_weights = np.asarray([float(getattr(task_bar.weights, n)) for n in names])
        return float(value), weights * d_weights, result, diagnostics

    log_weights = jnp.log(jnp.asarray([float(getattr(task.weights, n)) for n in names]))
    state = optimizer.init(log_weights)
    record = dict(loss=[], log_weights=[], gradients=[], status=[], iterations=[])
    previous, best, stopped = warm_start, None, f"{steps} steps"
    for step in range(steps):
        value, slope, result, diagnostics = evaluate(log_weights, previous)
        record["loss"].append(value)
        record["log_weights"].append(np.asarray(log_weights))
        record["gradients"].append(slope)
        record["status"].append(int(result.solution.status))
        record["iterations"].append(int(result.solution.iterations))
        if callback is not None:
            callback(step, value, {n: float(np.exp(v)) for n, v in zip(names, np.asarray(log_weights))})
        if result.status is not ip.Status.CONVERGED:
            stopped = f"solve did not converge at step {step}: {result.status.message}"
            break
        if best is None or value < best[0]:
            best = (value, log_weights, result)
        if not bool(diagnostics.reliable(max_residual)) or not np.all(np.isfinite(slope)) or not np.isfinite(value):
            stopped = (f"no reliable gradient at step {step}: adjoint residual {float(diagnostics.residual):.2g}, "
                       f"factored {bool(diagnostics.factored)}, loss {value:.6g}")
            break
        if value <= tolerance:
            stopped = f"loss {value:.6g} ≤ tolerance {tolerance:.6g} at step {step}"
            break
        updates, state = optimizer.update(jnp.asarray(slope), state, log_weights)
        log_weights = optax.apply_updates(log_weights, updates)
        previous = result
    final = best if best is not None else (record["loss"][-1], log_weights, result)
    return TuningResult(
        names=names, weights=_with_weights(task, names, final[1]).weights,
        loss=np.asarray(record["loss"]), log_weights=np.asarray(record["log_weights"]),
        gradients=np.asarray(record["gradients"]), status=np.asarray(record["status"]),
        iterations=np.asarray(record["iterations"]), stopped=stopped, solution=final[2],
    )
