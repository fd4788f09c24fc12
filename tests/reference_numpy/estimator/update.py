"""One estimator update with a batch of new records (:func:`update`): initialisation,
robust refinement and safeguards, in that order (the package doc).

:func:`update` chains named steps, each a pure function of arrays (batch shape ``B``, ``...``
below): forgetting (:func:`_forgotten_prior`), the raw window (:func:`_merge_window`), the
pseudo-linear initialisation (:func:`_initialise`), the global re-check (:func:`_recheck`),
the innovation gate (:func:`_innovation_gate`), the robust refinement (:func:`_refine`), the
marginalisation of the rows leaving the window (:func:`_marginalise_leaving`), the score test
(:func:`_consistency`) and the two windows' advance (:func:`_advance_range_window`,
:func:`_advance_window`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planner.params import Channel
from planner.sensing import COMPONENTS, SensingComponent
from tests.reference_numpy.estimator import memory as rmem
from tests.reference_numpy.estimator.initialisation import _distance_scale, _pl_cost, _pl_range_rows, _pl_rows, _pl_solve, _range_scale, _schur_prior
from tests.reference_numpy.estimator.linalg import _det3, _normalised_det
from tests.reference_numpy.estimator.robust import _accumulate, _Eval, _evaluate, _Gate, _lm_iterations, _Rows, _rows
from tests.reference_numpy.estimator.safeguards import _score_test
from tests.reference_numpy.estimator.state import (
    BoolArray,
    EstimatorConfig,
    EstimatorState,
    FloatArray,
    Measurements,
    _check,
    _concat,
    _rows_of,
    _scatter,
    _take,
)


@dataclass(frozen=True)
class _Prior:
    """Information-form summary of the marginalised records (internal): their cost
    ½xᵀΛx − ηᵀx with Λ = ``information`` (..., 3, 3), m⁻², η = ``vector`` (..., 3), m⁻¹, and
    their Fisher information ``fisher`` (..., 3, 3), m⁻²."""

    information: FloatArray
    fisher: FloatArray
    vector: FloatArray


@dataclass(frozen=True)
class _Start:
    """Where this call's refinement starts (internal): the estimate x (..., 3), m, ENU, the
    prior, which elements are initialised, which start afresh (initialised, moved or suspect:
    Huber iterations) and which run ``init_iterations`` (initialised or moved this call)."""

    x: FloatArray
    prior: _Prior
    initialised: BoolArray
    fresh_start: BoolArray
    long_run: BoolArray


@dataclass(frozen=True)
class _Refined:
    """The refinement's result (internal): estimate x (..., 3), m; the evaluation at the last
    iterate x_lin; there the gradient g (..., 3), m⁻¹, scoring matrix H and Fisher information
    F (..., 3, 3), m⁻² (prior included in g and H, not in F); ``run``: iterations ran."""

    x: FloatArray
    ev: _Eval
    g: FloatArray
    H: FloatArray
    F: FloatArray
    x_lin: FloatArray
    run: bool


def _check_windows(state: EstimatorState, config: EstimatorConfig) -> None:
    """Raise ValueError when ``state`` was not created with ``config``'s window sizes."""
    W = config.window_rows
    if state.window.count != W:
        raise ValueError(f"EstimatorState: window has {state.window.count} rows, config.window_rows is {W}")
    if state.range_memory.cells != config.range_memory_cells:
        raise ValueError(
            f"EstimatorState: range memory has {state.range_memory.cells} cells, config.range_memory_cells is {config.range_memory_cells}"
        )
    if state.range_window.count != config.recheck_window_rows:
        raise ValueError(
            f"EstimatorState: range window has {state.range_window.count} rows, config.recheck_window_rows is {config.recheck_window_rows}"
        )


def _forgotten_prior(state: EstimatorState, config: EstimatorConfig) -> _Prior:
    """The prior after forgetting (package doc, step 4): Λ, F and η times λ, and times
    λ·``suspect_deflation`` for a suspect element (it keeps a deflated prior)."""
    lam = config.forgetting
    deflate = np.where(state.suspect, lam * config.suspect_deflation, lam)
    return _Prior(
        state.prior_information * deflate[..., None, None],
        state.prior_fisher * deflate[..., None, None],
        state.prior_vector * deflate[..., None],
    )


def _merge_window(state: EstimatorState, new: Measurements, new_row_ok: BoolArray, config: EstimatorConfig) -> tuple[Measurements, FloatArray]:
    """All rows of this call, window first (oldest), new last, and their forgetting weights
    λ^age (0 for an invalid row); with a window, the most recent valid rows sorted to the end
    (stable: by validity, then by age)."""
    lam = config.forgetting
    if config.window_rows == 0:
        return new, np.where(new_row_ok, 1.0, 0.0)
    allm = _concat(state.window, new)
    weight = np.concatenate((state.window_weight * lam, np.where(new_row_ok, 1.0, 0.0)), axis=-1)
    if new.count > 0:
        valid = np.concatenate((np.isfinite(state.window.positions_m[..., 0]), new_row_ok), axis=-1)
        order = np.argsort(valid, axis=-1, kind="stable")
        allm = _take(allm, order)
        weight = np.take_along_axis(weight, order, axis=-1)
    return allm, weight


def _initialise(
    state: EstimatorState,
    new_rows: _Rows,
    prior: _Prior,
    pl: tuple[FloatArray, FloatArray],
    dropped: tuple[FloatArray, FloatArray],
    channel: Channel,
    config: EstimatorConfig,
    M: int,
) -> tuple[_Start, FloatArray, FloatArray]:
    """Pseudo-linear initialisation (package doc, step 1) of the elements not yet initialised.

    The new records' PL equations join the system ``pl`` = (A (..., 4, 4), b (..., 4)) of the
    element; where it becomes solvable the estimate is its solution (clipped to the search box)
    and the records dropped before initialisation (``dropped``) become the prior, R
    marginalised out (:func:`_schur_prior`). Returns the start and the new (A, b).
    """
    bshape = state.batch_shape
    pl_A, pl_b = pl
    x = state.estimate_m
    initialised = state.initialised
    todo = ~initialised
    long_run = np.zeros(bshape, dtype=bool)  # elements that get init_iterations this call
    fresh_start = state.suspect & state.initialised  # initialised, moved or suspect
    if M > 0 and np.any(todo):
        # Pseudo-linear equations of the new records (only needed until initialisation).
        sub = new_rows.subset(todo)
        A_new, b_new = _pl_rows(sub, _distance_scale(sub, config), channel)
        pl_A = pl_A.copy()
        pl_b = pl_b.copy()
        pl_A[todo] += A_new
        pl_b[todo] += b_new
        x_init, ok = _pl_solve(pl_A[todo], pl_b[todo], config)
        ok &= _determined(pl_A[todo], config)
        just = np.zeros(bshape, dtype=bool)
        just[todo] = ok
        x = x.copy()
        x[just] = config.clip(x_init[ok])
        # Records dropped before initialisation become the prior (R marginalised out).
        lam_d, eta_d = _schur_prior(*dropped)
        prior = _Prior(
            np.where(just[..., None, None], lam_d, prior.information),
            np.where(just[..., None, None], lam_d, prior.fisher),
            np.where(just[..., None], eta_d, prior.vector),
        )
        initialised = initialised | just
        fresh_start = fresh_start | just
        long_run = long_run | just
    return _Start(x, prior, initialised, fresh_start, long_run), pl_A, pl_b


def _determined(A: FloatArray, config: EstimatorConfig) -> BoolArray:
    """(n,) the PL systems A (n, 4, 4) that determine the source well enough to initialise
    from: with squared-range equations (a range without a bearing), any solvable one; else
    (every record with a bearing), one whose weakest direction has a PL standard deviation at most ``init_max_relative_sigma`` × the weights'
    distance ``init_distance_m`` (a bearing's weight is 1/(σ_b² D²) at that D, so the ratio is
    the relative uncertainty whatever the true distance). Two nearly parallel bearings solve
    but fix the point along their lines only to tens of metres; an estimate initialised there
    and the prior linearised at it stay biased for hundreds of steps."""
    has_r = A[:, 3, 3] > 1e-300
    if config.init_max_relative_sigma is None or np.all(has_r):
        return np.ones(A.shape[0], dtype=bool)
    lam_min = np.linalg.eigvalsh(A[:, :3, :3])[:, 0]
    limit = config.init_max_relative_sigma * config.init_distance_m
    return has_r | (lam_min * limit * limit >= 1.0)


def _recheck_due(state: EstimatorState, config: EstimatorConfig, M: int) -> bool:
    """The global re-check runs in every ``recheck_every``-th call that brings records."""
    return config.recheck_every > 0 and M > 0 and (state.calls + 1) % config.recheck_every == 0


def _recheck(
    state: EstimatorState,
    start: _Start,
    new_rows: _Rows,
    pr: tuple[FloatArray, FloatArray],
    range_weight: FloatArray,
    memory: rmem.RangeMemory,
    channel: Channel,
    config: EstimatorConfig,
    M: int,
) -> _Start:
    """Global re-check (package doc, step 3). The candidate is the squared-range PL solution of
    all past ranges (the summary ``pr`` = (A, b) plus the ranges still in the range window,
    weighted at the previous estimate).

    With the range ``memory`` (``range_memory_cells`` > 0), an element that has used only
    ranges is re-checked by :func:`_recheck_memory` instead, on the exact likelihood of every
    range so far. The others move to the candidate when the PL cost drops by more than
    ``recheck_threshold`` and the new records prefer it (their full likelihood, ½ ln σ_r²
    included: comparing distant candidates with σ_r evaluated at each would favour the farther
    one); their prior becomes the PL summary, of which only ``recheck_trust`` is claimed."""
    x_prev = state.estimate_m
    pr_A, pr_b = pr
    if _recheck_due(state, config, M) and np.any(state.initialised):
        # The re-check's system: the summary plus the ranges still waiting in the range
        # window, weighted at the previous estimate.
        pend = _rows(state.range_window, range_weight, channel, config)
        A_p, b_p = _pl_range_rows(pend, _range_scale(x_prev, state.initialised, pend, config), channel.gamma)
        sys_A, sys_b = pr_A + A_p, pr_b + b_p
    else:
        sys_A, sys_b = pr_A, pr_b
    recheck = state.initialised & (np.einsum("...ii->...", sys_A) > 0.0)
    if not (_recheck_due(state, config, M) and np.any(recheck)):
        return start
    x_pl, ok = _pl_solve(sys_A[recheck], sys_b[recheck], config)
    cand = x_prev.copy()
    cand[recheck] = config.clip(np.where(ok[:, None], x_pl, x_prev[recheck]))
    fresh = new_rows.masked(start.initialised)
    c_prev = _evaluate(x_prev, fresh, channel, config.huber_k, True, cost_only=True)
    by_memory = recheck & ~state.angles_used if config.range_memory_cells > 0 else np.zeros_like(recheck)
    if np.any(by_memory):
        start = _recheck_memory(start, x_prev, cand, by_memory, fresh, memory, channel, config)
    drop = _pl_cost(sys_A, sys_b, x_prev) - _pl_cost(sys_A, sys_b, cand)
    c_cand = _evaluate(cand, fresh, channel, config.huber_k, True, cost_only=True)
    move = recheck & ~by_memory & (drop > config.recheck_threshold) & (c_cand < c_prev)
    if not np.any(move):
        return start
    # The prior linearised in the other basin is replaced by the PL summary of the ranges
    # (R marginalised out); the past bearings' information is dropped. Claimed information
    # after a move: only ``recheck_trust`` of the PL summary (the squared-range PL solution can
    # be biased, e.g. by NLOS ranges; the records that follow rebuild the information at the
    # new estimate).
    lam_r, eta_r = _schur_prior(sys_A, sys_b)
    return _moved(start, move, cand, _Prior(lam_r, lam_r * config.recheck_trust, eta_r))


def _moved(start: _Start, move: BoolArray, x: FloatArray, prior: _Prior) -> _Start:
    """The start with the elements ``move`` at ``x`` (..., 3), m, with ``prior`` in place of
    theirs, afresh (Huber iterations, ``init_iterations``)."""
    return dataclasses.replace(
        start,
        x=np.where(move[..., None], x, start.x),
        prior=_Prior(
            np.where(move[..., None, None], prior.information, start.prior.information),
            np.where(move[..., None, None], prior.fisher, start.prior.fisher),
            np.where(move[..., None], prior.vector, start.prior.vector),
        ),
        fresh_start=start.fresh_start | move,
        long_run=start.long_run | move,
    )


def _recheck_memory(
    start: _Start,
    x_prev: FloatArray,
    cand: FloatArray,
    use: BoolArray,
    fresh: _Rows,
    memory: rmem.RangeMemory,
    channel: Channel,
    config: EstimatorConfig,
) -> _Start:
    """The re-check on the exact likelihood of the range memory and this call's ranges, for the
    elements ``use`` (initialised, range records only so far). The previous estimate and the
    best start of another basin (:func:`planner.estimator.memory.best_start`, from the PL
    candidate ``cand``) are each polished to their basin's optimum
    (:func:`planner.estimator.memory.polish`); when the previous estimate is less likely than
    the better optimum by more than ``recheck_likelihood_drop``, it moves there, and its prior,
    linearised where the estimate was, becomes the memory's cost (every past range)
    re-linearised at the new point and claimed in full (it is the likelihood, not the PL cost)."""
    gamma = channel.gamma
    fr = fresh.subset(use)
    mem = memory.subset(use)
    total = rmem.insert(mem, np.stack((fr.px, fr.py, fr.pz), axis=-1), fr.zr, fr.ar, fr.s0, config.range_memory_radius)
    xp = x_prev[use]
    both, nll_both = rmem.polish(total, np.stack((xp, rmem.best_start(total, xp, cand[use], gamma, config.clip))), gamma, config.clip)
    (x_here, x_there), (nll_here, nll_there) = both, nll_both
    x_best = np.where((nll_there < nll_here)[:, None], x_there, x_here)
    gain = rmem.nll(total, xp, gamma) - np.minimum(nll_here, nll_there)
    moved = rmem.has_ranges(total) & (gain > config.recheck_likelihood_drop)
    if not np.any(moved):
        return start
    move = _scatter(np.zeros_like(use), moved, use)
    x_new = _scatter(start.x, x_best, use)
    # The prior: the memory's cost (every past range) re-linearised at the new estimate.
    g, H = rmem.gradient_fisher(mem, x_best, gamma, config.range_cost == "ml")
    # Its Fisher information, as every other record's, includes the variance's dependence on
    # the distance (γ²/(2d²) per range; for NLOS ranges more than half of it).
    F = H if config.range_cost == "ml" else rmem.gradient_fisher(mem, x_best, gamma, True)[1]
    eta = _scatter(start.prior.vector, np.einsum("...ij,...j->...i", H, x_best) - g, use)
    H = _scatter(start.prior.information, H, use)
    F = _scatter(start.prior.fisher, F, use)
    return _moved(start, move, x_new, _Prior(H, F, eta))


def _innovation_gate(state: EstimatorState, config: EstimatorConfig) -> _Gate | None:
    """The innovation gate against the previous state (None when disabled or nothing is
    observable): tr(J⁻¹) = tr(adj J)/det J, m², bounds the variance of the previous estimate
    along any direction (J = ``state.information``)."""
    if config.gate_sigma is None or not np.any(state.observable):
        return None
    J = state.information
    det = _det3(J)
    tr_adj = (
        J[..., 1, 1] * J[..., 2, 2]
        - J[..., 1, 2] ** 2
        + J[..., 0, 0] * J[..., 2, 2]
        - J[..., 0, 2] ** 2
        + J[..., 0, 0] * J[..., 1, 1]
        - J[..., 0, 1] ** 2
    )
    use = state.observable & state.initialised & (det > 0.0)
    var_bound = np.where(use, tr_adj / np.where(use, det, 1.0), 0.0)
    return _Gate(var_bound, use, config.gate_sigma, config.gate_max_fraction)


def _redescend(tukey: bool, it: int, fresh: BoolArray, before: BoolArray, n_el: NDArray[np.int64]) -> bool | BoolArray:
    """Loss schedule (``config.loss == "tukey"``): where Tukey's biweight applies at iteration
    ``it``. Settled elements: Tukey; after a PL initialisation (``fresh`` and not initialised
    ``before``): Huber for the first half of their ``n_el`` iterations, then Tukey; a suspect
    or moved element: Huber for the whole call (Tukey's cost is flat far from the data,
    Huber's still points back to it)."""
    if not tukey:
        return False
    if not np.any(fresh):
        return True
    return ~fresh | ((2 * it >= n_el) & ~before)


def _refine(state: EstimatorState, start: _Start, rows: _Rows, gate: _Gate | None, channel: Channel, config: EstimatorConfig) -> _Refined:
    """Robust ML refinement (package doc, step 2): Levenberg-Marquardt (Fisher scoring)
    iterations, all elements at once. Each element runs its own number of iterations
    (``iterations``, or ``init_iterations`` where it is initialised or moved this call),
    whatever the rest of the batch does: a batch element computes exactly what the same
    records give with batch shape () (simulator = planner node). The innovation gate applies
    in the first evaluation. ``rows`` carry zero weights where not initialised."""
    active = start.initialised
    x, prior, fresh_start = start.x, start.prior, start.fresh_start
    ml = config.range_cost == "ml"
    run = bool(np.any(active)) and rows.zr.shape[-1] > 0
    n_short = config.iterations
    n_long = max(config.iterations, config.init_iterations)
    tukey = config.loss == "tukey"
    init_before = state.initialised
    n_elem = np.where(start.long_run, n_long, n_short)
    ev = _evaluate(
        x,
        rows,
        channel,
        config.huber_k,
        ml,
        gate=gate,
        redescend=_redescend(tukey, 0, fresh_start, init_before, n_elem),
        tukey_c=config.tukey_c,
        suspect_sigma=config.suspect_sigma,
    )
    rows = rows.with_weights(ev.ar, ev.aa, ev.ae)
    if not run:
        g, H, F = _accumulate(ev)
        g = g + np.einsum("...ij,...j->...i", prior.information, x) - prior.vector
        H = H + prior.information
        return _Refined(x, ev, g, H, F, x, run)
    mu = np.full(state.batch_shape, config.lm_damping)
    x, mu, ev, g, H, F, x_lin = _lm_iterations(
        x,
        mu,
        rows,
        ev,
        prior.information,
        prior.vector,
        active,
        range(n_short),
        lambda it: _redescend(tukey, it, fresh_start, init_before, n_elem),
        channel,
        config,
    )
    sel = active & (n_elem > n_short)
    if n_long > n_short and np.any(sel):
        # The elements that need more iterations continue alone (batch subset).
        fs, ib, ne = fresh_start[sel], init_before[sel], n_elem[sel]
        xs, _, evs, gs, Hs, Fs, xls = _lm_iterations(
            x[sel],
            mu[sel],
            rows.subset(sel),
            None,
            prior.information[sel],
            prior.vector[sel],
            np.ones(ne.shape, dtype=bool),
            range(n_short, n_long),
            lambda it: _redescend(tukey, it, fs, ib, ne),
            channel,
            config,
        )
        x, g, H, F, x_lin = (_scatter(a, b, sel) for a, b in ((x, xs), (g, gs), (H, Hs), (F, Fs), (x_lin, xls)))
        scattered: dict[str, Any] = {f: _scatter_optional(getattr(ev, f), getattr(evs, f), sel) for f in _Eval.__dataclass_fields__}
        ev = dataclasses.replace(ev, **scattered)
    return _Refined(x, ev, g, H, F, x_lin, run)


def _marginalise_leaving(
    refined: _Refined,
    prior_used: _Prior,
    active: BoolArray,
    all_rows: tuple[Measurements, FloatArray],
    n_leave: int,
    dropped: tuple[FloatArray, FloatArray],
    channel: Channel,
    config: EstimatorConfig,
) -> tuple[_Prior, tuple[FloatArray, FloatArray]]:
    """Marginalise the rows leaving the window (the oldest ``n_leave``), linearised at x_lin:
    their cost ≈ ½ xᵀH_l x − (H_l x_lin − g_l)ᵀx + const joins the prior of the active
    elements. Before initialisation the leaving rows (of ``all_rows``, this call's records and
    their weights) join the dropped PL equations ``dropped`` = (A, b) instead. Returns the prior and the dropped (A, b)."""
    ev, g, H, F, x_lin = refined.ev, refined.g, refined.H, refined.F, refined.x_lin
    dr_A, dr_b = dropped
    if n_leave == ev.d.shape[-1]:
        gl = g - (np.einsum("...ij,...j->...i", prior_used.information, x_lin) - prior_used.vector)
        Hl = H - prior_used.information
        Fl = F
    else:
        gl, Hl, Fl = _accumulate(ev, slice(0, n_leave))
    add_vec = np.einsum("...ij,...j->...i", Hl, x_lin) - gl
    prior = _Prior(
        np.where(active[..., None, None], prior_used.information + Hl, prior_used.information),
        np.where(active[..., None, None], prior_used.fisher + Fl, prior_used.fisher),
        np.where(active[..., None], prior_used.vector + add_vec, prior_used.vector),
    )
    if config.window_rows > 0 and np.any(~active):
        leave = _rows(*all_rows, channel, config).sliced(slice(0, n_leave)).subset(~active)
        A_l, b_l = _pl_rows(leave, _distance_scale(leave, config), channel)
        dr_A = dr_A.copy()
        dr_b = dr_b.copy()
        dr_A[~active] += A_l
        dr_b[~active] += b_l
    return prior, (dr_A, dr_b)


def _consistency(
    state: EstimatorState,
    refined: _Refined,
    prior_used: _Prior,
    active: BoolArray,
    suspect: BoolArray,
    fisher: FloatArray,
    config: EstimatorConfig,
    M: int,
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray, FloatArray]:
    """Consistency (score) test of the recent records against the estimate
    (:func:`planner.estimator.safeguards._score_test`): a failed element becomes suspect and
    its reported information ``fisher`` (..., 3, 3), m⁻², is deflated by ``suspect_deflation``.
    Returns (S_H, S_v, T, suspect, fisher)."""
    score_H, score_v, consistency = state.score_matrix, state.score_vector, state.consistency
    if config.consistency_threshold is None or M == 0 or not refined.run:
        return score_H, score_v, consistency, suspect, fisher
    g, H, x_lin = refined.g, refined.H, refined.x_lin
    if config.window_rows == 0:
        g_new = g - (np.einsum("...ij,...j->...i", prior_used.information, x_lin) - prior_used.vector)
        H_new = H - prior_used.information
    else:
        K = refined.ev.d.shape[-1]
        g_new, H_new, _ = _accumulate(refined.ev, slice(K - M, K))
    score_H, score_v, consistency, fail = _score_test(
        state.score_matrix, state.score_vector, g_new, H_new, x_lin, refined.x, active, config.consistency_threshold, config
    )
    if np.any(fail):
        suspect = suspect | fail
        fisher = np.where(fail[..., None, None], fisher * config.suspect_deflation, fisher)
    return score_H, score_v, consistency, suspect, fisher


def _reported(
    x_prev: FloatArray, x: FloatArray, fisher: FloatArray, active: BoolArray, config: EstimatorConfig
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """The estimate (..., 3), m, ENU, its information (..., 3, 3), m⁻² (symmetrised; 0 where
    not initialised) and observability (package doc, step 5): initialised, finite and
    det J/(tr J/3)³ ≥ ``min_rcond``. A non-finite result keeps the previous estimate ``x_prev``."""
    fisher = 0.5 * (fisher + np.swapaxes(fisher, -1, -2))
    finite = np.all(np.isfinite(x), axis=-1) & np.all(np.isfinite(fisher), axis=(-1, -2))
    x = np.where(finite[..., None], x, x_prev)
    info = np.where((active & finite)[..., None, None], fisher, 0.0)
    observable = active & finite & (_normalised_det(info) >= config.min_rcond)
    return x, info, observable


def _scatter_optional(a: NDArray | None, b: NDArray | None, sel: BoolArray) -> NDArray | None:
    """:func:`_scatter`, or None where both are None (an evaluation without extra components)."""
    if a is None or b is None:
        if a is not None or b is not None:
            raise ValueError("evaluations: expected both or neither to carry extra components")
        return None
    return _scatter(a, b, sel)


def _head(m: Measurements, n: int) -> Measurements:
    """The first ``n`` rows of ``m``."""
    return _rows_of(m, slice(None, n))


def _tail(m: Measurements, n: int) -> Measurements:
    """The rows of ``m`` from the ``n``-th on."""
    return _rows_of(m, slice(n, None))


def _advance_range_window(
    state: EstimatorState,
    new: Measurements,
    new_row_ok: BoolArray,
    range_weight: FloatArray,
    pr: tuple[FloatArray, FloatArray],
    x: FloatArray,
    initialised: BoolArray,
    channel: Channel,
    config: EstimatorConfig,
) -> tuple[Measurements, FloatArray, FloatArray, FloatArray]:
    """The new ranges join the range window; the oldest rows leave it and join the re-check's
    squared-range summary ``pr`` = (A, b), weighted at this call's estimate x (a record's
    weight 1/(4D²σ_r²(D)) ∝ D⁻⁴ is frozen when it joins: a window of later estimates, not the
    first poor ones). Returns the range window, its weights and the summary (A, b)."""
    pr_A, pr_b = pr
    M = new.count
    if M == 0:
        return state.range_window, range_weight, pr_A, pr_b
    new_ranges = Measurements(new.positions_m, new.range_m, np.full(new.range_m.shape, np.nan), np.full(new.range_m.shape, np.nan), new.los)
    new_weight = np.where(new_row_ok & np.isfinite(new.range_m), 1.0, 0.0)
    if config.recheck_window_rows > 0:
        pool = _concat(state.range_window, new_ranges)
        pool_weight = np.concatenate((range_weight, new_weight), axis=-1)
        # Valid rows at the end, oldest first (stable sort): the first M rows leave.
        order = np.argsort(pool_weight > 0.0, axis=-1, kind="stable")
        pool = _take(pool, order)
        pool_weight = np.take_along_axis(pool_weight, order, axis=-1)
        leaving, leaving_weight = _head(pool, M), pool_weight[..., :M]
        range_window, range_weight = _tail(pool, M), pool_weight[..., M:]
    else:
        leaving, leaving_weight = new_ranges, new_weight
        range_window = state.range_window
    lrows = _rows(leaving, leaving_weight, channel, config)
    if np.any(lrows.ar > 0.0):
        A_r, b_r = _pl_range_rows(lrows, _range_scale(x, initialised, lrows, config), channel.gamma)
        pr_A = pr_A + A_r
        pr_b = pr_b + b_r
    return range_window, range_weight, pr_A, pr_b


def _advance_memory(memory: rmem.RangeMemory, new_rows: _Rows, keep: BoolArray, config: EstimatorConfig) -> rmem.RangeMemory:
    """The range memory with this call's ranges, for the elements ``keep`` (range records only
    so far: the others never use it)."""
    take = keep & np.any(new_rows.ar > 0.0, axis=-1)
    if config.range_memory_cells == 0 or not np.any(take):
        return memory
    r = new_rows.subset(take)
    sub = rmem.insert(memory.subset(take), np.stack((r.px, r.py, r.pz), axis=-1), r.zr, r.ar, r.s0, config.range_memory_radius)
    return memory.scattered(sub, take)


def _advance_window(state: EstimatorState, allm: Measurements, weight: FloatArray, config: EstimatorConfig) -> tuple[Measurements, FloatArray]:
    """The raw window after this call: the newest ``window_rows`` rows of ``allm`` and their
    weights (the state's window, unchanged, without one)."""
    W = config.window_rows
    if W == 0:
        return state.window, state.window_weight
    K = weight.shape[-1]
    return _tail(allm, K - W), weight[..., K - W :]


def update(
    state: EstimatorState,
    measurements: Measurements,
    channel: Channel,
    config: EstimatorConfig | None = None,
    components: Sequence[SensingComponent] = COMPONENTS,
) -> EstimatorState:
    """Incorporate new records and return the new state (pure function, inputs untouched).

    Args:
        state: previous state, batch shape ``B`` (``()`` for one planner).
        measurements: new records, ``positions_m`` of shape ``B + (M, 3)`` (m, ENU), angles in
            radians, NaN for absent values, ``los`` bool ``B + (M,)``. M may be 0.
        channel: the RSS channel (γ, σ_sh/γ LOS/NLOS, σ_b), eqs. (3)-(5).
        config: estimator configuration; must be the one ``state`` was created with.
        components: the measurement components (:data:`planner.sensing.COMPONENTS`): those
            other than range and bearing whose values ``measurements.extra_values`` carries
            join the robust refinement (not the pseudo-linear initialisation).

    Returns:
        The updated :class:`EstimatorState`; see the module docstring for the method.

    Raises:
        ValueError: shapes or dtypes that do not match the state.
    """
    config = EstimatorConfig() if config is None else config
    _check_windows(state, config)
    new = _check(measurements, state.batch_shape)
    lam = config.forgetting
    W, M = config.window_rows, new.count
    prior = _forgotten_prior(state, config)
    dropped = (state.pl_dropped_matrix * lam, state.pl_dropped_vector * lam)
    new_row_ok = np.isfinite(new.positions_m.sum(axis=-1))  # NaN/inf in any coordinate
    allm, weight = _merge_window(state, new, new_row_ok, config)
    rows = _rows(allm, weight, channel, config, components)
    K = W + M
    n_leave = K - W  # = M: the oldest M rows leave the window after this call
    new_rows = rows.sliced(slice(K - M, K)) if W == 0 else _rows(new, np.where(new_row_ok, 1.0, 0.0), channel, config, components)

    start, pl_A, pl_b = _initialise(state, new_rows, prior, (state.pl_matrix * lam, state.pl_vector * lam), dropped, channel, config, M)
    pr = (state.pl_range_matrix * lam, state.pl_range_vector * lam)
    range_weight = state.range_window_weight * lam
    memory = state.range_memory.forgotten(lam)
    start = _recheck(state, start, new_rows, pr, range_weight, memory, channel, config, M)
    active = start.initialised
    if not np.all(active):
        rows = rows.masked(active)

    refined = _refine(state, start, rows, _innovation_gate(state, config), channel, config)
    ev = refined.ev
    prior = start.prior
    # Information of everything used, linearised at x_lin (the last iterate evaluated).
    fisher = refined.F + prior.fisher
    suspect = active & np.any((ev.n_used >= 2.5) & (ev.n_big > config.suspect_fraction * ev.n_used), axis=-1)
    if n_leave > 0:
        prior, dropped = _marginalise_leaving(refined, start.prior, active, (allm, weight), n_leave, dropped, channel, config)
    score_H, score_v, consistency, suspect, fisher = _consistency(state, refined, start.prior, active, suspect, fisher, config, M)
    x, info, observable = _reported(state.estimate_m, refined.x, fisher, active, config)

    range_window, range_window_weight, pr_A, pr_b = _advance_range_window(
        state, new, new_row_ok, range_weight, pr, x, start.initialised, channel, config
    )
    window, window_weight = _advance_window(state, allm, weight, config)
    used = new_rows.used_count()
    angles_used = state.angles_used | np.any((new_rows.aa > 0.0) | (new_rows.ae > 0.0), axis=-1)
    for extra in new_rows.extra:
        angles_used = angles_used | np.any(extra.a > 0.0, axis=(-2, -1))
    memory = _advance_memory(memory, new_rows, ~angles_used, config)
    return EstimatorState(
        estimate_m=x,
        information=info,
        observable=observable,
        initialised=start.initialised,
        prior_information=prior.information,
        prior_fisher=prior.fisher,
        prior_vector=prior.vector,
        pl_matrix=pl_A,
        pl_vector=pl_b,
        pl_dropped_matrix=dropped[0],
        pl_dropped_vector=dropped[1],
        pl_range_matrix=pr_A,
        pl_range_vector=pr_b,
        range_window=range_window,
        range_window_weight=range_window_weight,
        range_memory=memory,
        angles_used=angles_used,
        window=window,
        window_weight=window_weight,
        measurement_count=state.measurement_count + used,
        suspect=suspect,
        score_matrix=score_H,
        score_vector=score_v,
        consistency=consistency,
        calls=state.calls + 1,
    )
