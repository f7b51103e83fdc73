"""The interior-point solver's settings (``Options``), its result codes (``Status``) and its fixed
constants, with IPOPT's names where they have one (Wächter & Biegler 2006)."""

import dataclasses
import enum
from typing import Callable

EQUALITIES = ("path_equality", "transition_equality")
INEQUALITIES = ("path_inequality", "transition_inequality")
GROUPS = EQUALITIES + INEQUALITIES

HISTORY_COLUMNS = ("objective", "violation", "stationarity", "barrier", "step_length", "regularisation", "linear_solves",
                   "restoration", "factorisations")

FILTER_SIZE = 128
REFINEMENT_STEPS = 10  # most refinements of a step towards the exact KKT system (while the residual falls)
# Refinement ends once the exact KKT residual is below this fraction of the right-hand side (or
# stops falling by 10 %). A tighter 1e-14 costs 8–10 solves per iteration on take-off for no
# fewer iterations (docs/design-decisions.md, "Iterative refinement to 1e-10").
REFINEMENT_RATIO = 1e-10
# The restoration phase minimises ½‖c‖² + (μ / RESTORATION_PENALTY) × barrier: IPOPT's weighs its
# ℓ1 infeasibility by ρ = 1000 against the barrier and its proximal term. (With μ itself, the
# barrier held walk-to-fly N = 20 at a violation of 0.5.)
RESTORATION_PENALTY = 1000.0
SOC_STEPS = 4  # second-order corrections per iteration (IPOPT's max_soc)
KAPPA_SIGMA = 1e10  # bound multipliers kept within this factor of μ / distance (IPOPT's κ_Σ)


class Status(enum.IntEnum):
    """Why a solve stopped."""

    CONVERGED = 0
    MAX_ITERATIONS = 1
    STALLED = 2  # feasible, but no acceptable step improves the objective any more
    NAN = 3  # a non-finite value appeared; the last finite iterate is returned
    RUNNING = 4
    # Infeasible, and the restoration phase found no point the filter accepts: a locally
    # infeasible problem, or a restoration that failed (``Solution.violation`` says how far from
    # feasible it stopped; with the restoration phase turned off, a line search that failed).
    INFEASIBLE = 5
    INTERRUPTED = 6  # stopped by the user (Ctrl-C) between iterations; the last iterate is returned
    TIME_LIMIT = 7  # stopped when its time budget ran out, between iterations; the last iterate is returned

    @property
    def message(self):
        return {
            Status.CONVERGED: "converged: feasibility, stationarity and complementarity within tolerance",
            Status.MAX_ITERATIONS: "stopped at the iteration limit before converging",
            Status.STALLED: "stalled: feasible, but no acceptable step improves the objective",
            Status.NAN: "a non-finite value appeared; returned the last finite iterate",
            Status.RUNNING: "running",
            Status.INFEASIBLE: "infeasible: the restoration phase found no acceptable point with the constraint "
                               "violation above tolerance (locally infeasible, or the restoration failed; see the "
                               "violation)",
            Status.INTERRUPTED: "interrupted before converging; returned the last iterate",
            Status.TIME_LIMIT: "stopped when the time budget ran out, before converging; returned the last iterate",
        }[self]


SLACK_STARTS = ("pushed", "guess")


@dataclasses.dataclass(frozen=True)
class Options:
    """Solver settings (static).

    tolerance: max constraint violation (the NLP's own units: |c|, distance of g to [l, u]);
    100× tighter than the paper's IPOPT ``constr_viol_tol``; stationarity: scaled dual
    infeasibility and complementarity (IPOPT's E₀ without the violation), the paper's IPOPT
    ``tol``; max_iterations: Newton iterations; barrier0: the first barrier parameter μ;
    barrier_factor, barrier_power: μ ← min(factor μ, μ^power) once the barrier problem is
    solved to barrier_tolerance_factor × μ, but not below barrier_min / 10 nor below
    stationarity / (barrier_tolerance_factor + 1) (IPOPT's floor: a barrier problem solved
    there meets the stationarity tolerance already); dual_regularisation: δ = 1/ρ of the
    equality rows; regularisation_decrease: the inertia correction's first δ_w > 0 is the last
    one needed times this (IPOPT's κ_w⁻ is 1/3), growing ×8 from there until the Newton matrix
    factors; line_search_steps: backtracking halvings; max_gradient: scaling target;
    max_rejections: consecutive rejected steps before the restoration phase (violation above
    tolerance) or ``STALLED``; max_short_steps, short_step: the restoration phase also starts
    after max_short_steps iterations in a row whose steps (rejected ones included) were shorter
    than short_step and that together cut the violation by less than 10 % (0 turns this
    off): a locally infeasible problem's Newton steps run into the bounds and are cut to
    ≈ 1e-4, which the line search accepts for 1000 iterations or more; max_filter_resets: how
    often, per barrier parameter, a step that only the filter rejected empties the filter
    (IPOPT's filter reset heuristic); max_soft_steps: how many
    consecutive iterations may take a soft-restoration step (IPOPT's: when the line search
    rejects every trial, the step to the fraction-to-boundary length is taken if it cuts the
    primal–dual error of the barrier problem by 0.9999; 0 turns it off);
    max_restoration_iterations: iterations of one restoration phase before ``INFEASIBLE`` (0
    turns the phase off: then ``max_rejections`` rejected steps far from feasible end the solve
    ``INFEASIBLE``); slack_start: where the inequality rows' slacks start: ``"pushed"`` (IPOPT's
    rule, the default) at the rows' values at the starting point pushed inside its bounds,
    ``"guess"`` at their values at the guess as given (with it the published walk-to-fly does
    not converge; docs/design-decisions.md, "The slack start"); ipopt_slacks: δ_w regularises the slacks as it
    does (Z, θ) (IPOPT's δ_s = δ_w; off: (Z, θ) only): with the pushed start, the slacks treated
    as IPOPT treats them, whose steps ours then follow (tools/follow_ipopt.py);
    take-off-and-landing converges in fewer iterations with it, take-off lands on an optimum
    that fails ``validate`` (docs/design-decisions.md);
    relaxation: κ_σ of the relaxation homotopy (Scholtes' relaxation driven by the barrier
    parameter, as interior-point methods for MPCCs do: Raghunathan & Biegler 2005): the bounds of
    the rows that the NLP marks (``StagewiseNLP.path_relaxation``: the complementarity rows)
    widened by σ = κ_σ (μ − μ_floor) / s_f in the rows' units (s_f the cost's scaling factor:
    μ / s_f is the barrier parameter in the NLP's cost units), so that σ changes only with μ,
    when the filter is reset anyway, and vanishes at the barrier floor, where the solve
    converges to the NLP itself; 0 (default) turns it off. 1e-3 took the published take-off
    from 307 to 114 iterations and the jump from 219 to 97, but leads the 14-knot take-off to an
    optimum of the published NLP that pushes with a corner in the air (docs/design-decisions.md);
    progress: called on the host after every iteration as progress(iteration, record) with
    record the history row (``HISTORY_COLUMNS``); None (default) stays silent.
    """

    tolerance: float = 1e-6
    stationarity: float = 1e-4
    max_iterations: int = 3000
    barrier0: float = 0.1
    barrier_min: float = 1e-11
    barrier_factor: float = 0.2
    barrier_power: float = 1.5
    barrier_tolerance_factor: float = 10.0
    dual_regularisation: float = 1e-8
    regularisation_decrease: float = 1e-3
    line_search_steps: int = 30
    max_gradient: float = 100.0
    max_rejections: int = 15
    max_short_steps: int = 15
    short_step: float = 1e-3
    max_filter_resets: int = 5
    max_soft_steps: int = 10
    bound_push: float = 1e-2
    max_restoration_iterations: int = 100
    slack_start: str = "pushed"
    ipopt_slacks: bool = False
    relaxation: float = 0.0
    progress: Callable | None = None

    def __post_init__(self):
        if self.slack_start not in SLACK_STARTS:
            raise ValueError(f"Options.slack_start must be one of {SLACK_STARTS}, got {self.slack_start!r}")
        if not 0 < self.regularisation_decrease <= 1:
            raise ValueError(f"Options.regularisation_decrease must be in (0, 1], got {self.regularisation_decrease!r}")
        if not 0 < self.short_step <= 1:
            raise ValueError(f"Options.short_step must be in (0, 1], got {self.short_step!r}")
        if not self.relaxation >= 0:
            raise ValueError(f"Options.relaxation must be ≥ 0 (0 turns the homotopy off), got {self.relaxation!r}")
        if self.max_short_steps < 0:
            raise ValueError(f"Options.max_short_steps must be ≥ 0 (0 turns the rule off), got {self.max_short_steps!r}")

    @property
    def barrier_floor(self):
        """The smallest μ: barrier_min / 10, or stationarity / (barrier_tolerance_factor + 1)
        if larger (a barrier problem solved there meets the stationarity tolerance already)."""
        return max(self.barrier_min / 10, self.stationarity / (self.barrier_tolerance_factor + 1))


def iteration_options(options):
    """``options`` with the settings only ``start`` reads (barrier0, bound_push, max_gradient,
    slack_start) at their defaults; the state carries bound_push and max_gradient as data for
    ``advance``'s first pass (``state.FirstPass``). ``advance`` gives the same result with
    either (tested), so one compiled ``advance`` (options are static) serves every start that
    differs only there: a warm start's barrier settings, say."""
    return dataclasses.replace(options, barrier0=Options.barrier0, bound_push=Options.bound_push,
                               max_gradient=Options.max_gradient, slack_start=Options.slack_start)
