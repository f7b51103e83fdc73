"""The interior-point solver's data: its state between iterations (``State``: the primal–dual
``Iterate``, the ``filter.Filter``, the ``Counters`` and the constants fixed at the start) and
its result (``Solution``, ``Multipliers``)."""

import dataclasses

import jax

from jaxmm.solver.filter import Filter


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Multipliers:
    """Multipliers of every constraint group (same shapes as the residuals), in the NLP's units:
    the Lagrangian is f + Σ λ·c (inequalities: λ > 0 at an active upper bound, < 0 at a lower)."""

    path_equality: jax.Array
    transition_equality: jax.Array
    path_inequality: jax.Array
    transition_inequality: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Solution:
    """Result of a solve: the optimum (scaled NLP variables), multipliers, why it stopped and
    statistics. ``status`` is a ``Status`` code; ``history`` (max_iterations, 9) has one row per
    iteration with the columns of ``HISTORY_COLUMNS`` (step length 0: step rejected; linear
    solves: block solves with the factor, refinements and second-order corrections included;
    restoration: 1 in an iteration of the restoration phase, whose regularisation is its damping ζ,
    0 otherwise; factorisations: the inertia correction's work, the diagonal blocks factored over
    all its attempts divided by the number of blocks: 1 when the first attempt worked, more for
    each that failed, a failed one counting the blocks it factored and the indefinite one);
    rows past ``iterations`` are NaN. ``barrier_updates`` counts the decreases of μ (outer iterations).
    ``bound_multipliers`` (lower, upper), each a tuple over (Z, θ, path slacks, transition
    slacks) in the solver's scaling, are for warm starts. ``slacks`` (path, transition): the
    inequality rows' slacks, scaled by the row factors; ``scaling`` = (cost factor (), per-row
    factors of the four groups): the solver minimised cost factor × f subject to row factor ×
    c. Both let ``sensitivity`` rebuild the barrier terms in the NLP's units."""

    Z: jax.Array
    theta: jax.Array
    multipliers: Multipliers
    status: jax.Array
    objective: jax.Array
    violation: jax.Array
    violation_per_group: dict
    stationarity: jax.Array
    iterations: jax.Array
    barrier_updates: jax.Array
    history: jax.Array
    bound_multipliers: tuple
    slacks: tuple
    scaling: tuple


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Iterate:
    """The primal–dual point in the solver's scaling: P = (Z (K, nz), θ (ng,), path slacks (K, mg),
    transition slacks (K − 1, mh)); y, the four groups' multipliers; zl, zu, the bound
    multipliers per primal leaf (0 where there is no bound)."""

    P: tuple
    y: tuple
    zl: tuple
    zu: tuple


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Counters:
    """soft_steps: consecutive soft-restoration steps (0: the line search accepted the last
    step); rejections: consecutive rejected steps; short_steps: consecutive iterations with steps
    below ``Options.short_step`` and < 10 % less violation, short_violation: the violation where
    they began; restoration_iterations: iterations of the current restoration phase;
    barrier_updates: decreases of μ."""

    soft_steps: jax.Array
    rejections: jax.Array
    short_steps: jax.Array
    short_violation: jax.Array
    restoration_iterations: jax.Array
    barrier_updates: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SoftStep:
    """A soft-restoration step taken on trust. IPOPT keeps such a step when it lowers the
    barrier problem's primal–dual error to 0.9999 of the error where it started; the error at
    the new point needs the Lagrangian's gradient there, which the next iteration's derivatives
    compute, so the test is made at the next iteration, and a step that fails it is undone
    (``refused`` replaces the state) before anything else is computed from it. pending: whether
    the state's iterate is such a step; reference: the error it must beat; refused: the
    ``State`` had the step been turned down (its own ``soft.refused`` is None)."""

    pending: jax.Array
    reference: jax.Array
    refused: object = None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FirstPass:
    """What the first pass of ``advance`` completes of a state that ``start`` left unfinished.
    ``start`` evaluates nothing of the NLP (it would compile the NLP's functions a second time):
    the first pass evaluates the residuals at the starting point at the line search's call site
    and, without a given scaling, IPOPT's gradient-based scaling from the derivatives that the
    iteration evaluates there; then it puts the slacks, multipliers and filter envelope in that
    scaling (``interior_point._in_scaling``). pending: whether that pass is still to run; scale:
    whether it computes the scaling (False: ``start`` was given one, held in ``State.scaling``);
    rows, rows_given: the inequality rows where the slacks start ((K, mg), (K − 1, mh), the
    NLP's units) when ``start`` evaluated them (``slack_start="guess"``; otherwise the rows
    at the starting point, which the pass evaluates); bound_push, max_gradient: the
    ``Options`` of ``start`` (data, so that one compiled ``advance`` serves every start)."""

    pending: jax.Array
    scale: jax.Array
    rows: tuple
    rows_given: jax.Array
    bound_push: jax.Array
    max_gradient: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """The solver between two iterations (``start``, ``advance``, ``finish``).

    iterate: the ``Iterate``; residuals: the NLP's ``stagewise.Residuals`` at it; mu: the barrier
    parameter; regularisation: the last nonzero δ_w that was needed (0: none yet); forced: the
    δ_w to start from after a rejected step (0 after an accepted one); filter; counters;
    iterations, status (a ``Status`` code), violation (max, the NLP's units), stationarity (the
    last iteration's optimality error), history (``Solution.history``); scaling: (cost factor,
    per-row factors of the four groups); theta_max: the filter's envelope on the infeasibility,
    theta_min: the infeasibility below which Armijo steps on the barrier function may be taken
    (both from the starting point); restoring: in the restoration phase; restoration_theta: the
    infeasibility where it started; soft: the ``SoftStep`` whose test is still to be made;
    first_pass: the ``FirstPass`` that completes the state of ``start``."""

    iterate: Iterate
    residuals: object
    mu: jax.Array
    regularisation: jax.Array
    forced: jax.Array
    filter: Filter
    counters: Counters
    iterations: jax.Array
    status: jax.Array
    violation: jax.Array
    stationarity: jax.Array
    history: jax.Array
    scaling: tuple
    theta_max: jax.Array
    theta_min: jax.Array
    restoring: jax.Array
    restoration_theta: jax.Array
    soft: SoftStep
    first_pass: FirstPass
