"""One estimator update with a batch of new records (:func:`update`): initialisation,
robust refinement and safeguards, in that order (the package doc)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from planner.estimator.initialisation import _distance_scale, _pl_cost, _pl_range_rows, _pl_rows, _pl_solve, _range_scale, _schur_prior
from planner.estimator.linalg import _det3, _normalised_det
from planner.estimator.robust import _accumulate, _Eval, _evaluate, _Gate, _lm_iterations, _rows
from planner.estimator.safeguards import _score_test
from planner.estimator.state import BoolArray, EstimatorConfig, EstimatorState, Measurements, _check, _concat, _scatter, _take
from planner.params import Channel


def update(
    state: EstimatorState,
    measurements: Measurements,
    channel: Channel,
    config: EstimatorConfig | None = None,
) -> EstimatorState:
    """Incorporate new records and return the new state (pure function, inputs untouched).

    Args:
        state: previous state, batch shape ``B`` (``()`` for one planner).
        measurements: new records, ``positions_m`` of shape ``B + (M, 3)`` (m, ENU), angles in
            radians, NaN for absent values, ``los`` bool ``B + (M,)``. M may be 0.
        channel: the RSS channel (γ, σ_sh/γ LOS/NLOS, σ_b), eqs. (3)-(5).
        config: estimator configuration; must be the one ``state`` was created with.

    Returns:
        The updated :class:`EstimatorState`; see the module docstring for the method.

    Raises:
        ValueError: shapes or dtypes that do not match the state.
    """
    config = EstimatorConfig() if config is None else config
    bshape = state.batch_shape
    W = config.window_rows
    if state.window.count != W:
        raise ValueError(f"EstimatorState: window has {state.window.count} rows, config.window_rows is {W}")
    if state.range_window.count != config.recheck_window_rows:
        raise ValueError(
            f"EstimatorState: range window has {state.range_window.count} rows, config.recheck_window_rows is {config.recheck_window_rows}"
        )
    new = _check(measurements, bshape)
    lam = config.forgetting
    M = new.count

    # Forgetting, then all rows: window first (oldest), new last.
    # A suspect element (see EstimatorState.suspect) keeps a deflated prior.
    deflate = np.where(state.suspect, lam * config.suspect_deflation, lam)
    prior_info = state.prior_information * deflate[..., None, None]
    prior_fisher = state.prior_fisher * deflate[..., None, None]
    prior_vec = state.prior_vector * deflate[..., None]
    pl_A = state.pl_matrix * lam
    pl_b = state.pl_vector * lam
    dr_A = state.pl_dropped_matrix * lam
    dr_b = state.pl_dropped_vector * lam
    new_row_ok = np.isfinite(new.positions_m.sum(axis=-1))  # NaN/inf in any coordinate
    if W > 0:
        allm = _concat(state.window, new)
        weight = np.concatenate((state.window_weight * lam, np.where(new_row_ok, 1.0, 0.0)), axis=-1)
        if M > 0:
            # Keep the most recent valid rows at the end (stable: by validity, then by age).
            valid = np.concatenate((np.isfinite(state.window.positions_m[..., 0]), new_row_ok), axis=-1)
            order = np.argsort(valid, axis=-1, kind="stable")
            allm = _take(allm, order)
            weight = np.take_along_axis(weight, order, axis=-1)
    else:
        allm, weight = new, np.where(new_row_ok, 1.0, 0.0)
    rows = _rows(allm, weight, channel, config)
    K = W + M
    n_leave = K - W  # = M: the oldest M rows leave the window after this call
    new_rows = rows.sliced(slice(K - M, K)) if W == 0 else _rows(new, np.where(new_row_ok, 1.0, 0.0), channel, config)

    x_prev = state.estimate_m
    initialised = state.initialised
    x = x_prev
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
        just = np.zeros(bshape, dtype=bool)
        just[todo] = ok
        x = x.copy()
        x[just] = config.clip(x_init[ok])
        # Records dropped before initialisation become the prior (R marginalised out).
        lam_d, eta_d = _schur_prior(dr_A, dr_b)
        prior_info = np.where(just[..., None, None], lam_d, prior_info)
        prior_fisher = np.where(just[..., None, None], lam_d, prior_fisher)
        prior_vec = np.where(just[..., None], eta_d, prior_vec)
        initialised = initialised | just
        fresh_start = fresh_start | just
        long_run = long_run | just
    # Global re-check (every recheck_every calls): the squared-range PL solution of all past
    # ranges against the current estimate; move there when the PL cost drops by more than the
    # threshold AND the new records prefer it.
    pr_A = state.pl_range_matrix * lam
    pr_b = state.pl_range_vector * lam
    range_weight = state.range_window_weight * lam
    if config.recheck_every > 0 and M > 0 and (state.calls + 1) % config.recheck_every == 0 and np.any(state.initialised):
        # The re-check's system: the summary plus the ranges still waiting in the range
        # window, weighted at the previous estimate.
        pend = _rows(state.range_window, range_weight, channel, config)
        A_p, b_p = _pl_range_rows(pend, _range_scale(x_prev, state.initialised, pend, config), channel.gamma)
        sys_A, sys_b = pr_A + A_p, pr_b + b_p
    else:
        sys_A, sys_b = pr_A, pr_b
    recheck = state.initialised & (np.einsum("...ii->...", sys_A) > 0.0)
    if config.recheck_every > 0 and M > 0 and (state.calls + 1) % config.recheck_every == 0 and np.any(recheck):
        x_pl, ok = _pl_solve(sys_A[recheck], sys_b[recheck], config)
        cand = x_prev.copy()
        cand[recheck] = config.clip(np.where(ok[:, None], x_pl, x_prev[recheck]))
        drop = _pl_cost(sys_A, sys_b, x_prev) - _pl_cost(sys_A, sys_b, cand)
        fresh = new_rows.with_weights(
            np.where(initialised[..., None], new_rows.ar, 0.0),
            np.where(initialised[..., None], new_rows.aa, 0.0),
            np.where(initialised[..., None], new_rows.ae, 0.0),
        )
        # The fresh records judge with the full likelihood (½ ln σ_r² included): comparing
        # distant candidates with σ_r evaluated at each would favour the farther one.
        c_prev = _evaluate(x_prev, fresh, channel, config.huber_k, True, cost_only=True)
        c_cand = _evaluate(cand, fresh, channel, config.huber_k, True, cost_only=True)
        move = recheck & (drop > config.recheck_threshold) & (c_cand < c_prev)
        if np.any(move):
            # The prior linearised in the other basin is replaced by the PL summary of the
            # ranges (R marginalised out); the past bearings' information is dropped.
            lam_r, eta_r = _schur_prior(sys_A, sys_b)
            x = np.where(move[..., None], cand, x)
            prior_info = np.where(move[..., None, None], lam_r, prior_info)
            # Claimed information after a move: only ``recheck_trust`` of the PL summary (the
            # squared-range PL solution can be biased, e.g. by NLOS ranges; the records that
            # follow rebuild the information at the new estimate).
            prior_fisher = np.where(move[..., None, None], lam_r * config.recheck_trust, prior_fisher)
            prior_vec = np.where(move[..., None], eta_r, prior_vec)
            fresh_start = fresh_start | move
            long_run = long_run | move
    active = initialised
    if not np.all(active):
        act = active[..., None]
        rows = rows.with_weights(np.where(act, rows.ar, 0.0), np.where(act, rows.aa, 0.0), np.where(act, rows.ae, 0.0))

    # Innovation gate against the previous state, applied in the first evaluation.
    gate = None
    if config.gate_sigma is not None and np.any(state.observable):
        J = state.information
        det = _det3(J)
        # tr(J⁻¹) = tr(adj J)/det J ≥ the variance of the estimate along any direction.
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
        gate = _Gate(var_bound, use, config.gate_sigma, config.gate_max_fraction)

    # Levenberg-Marquardt (Fisher scoring) iterations, all elements at once. Each element runs
    # its own number of iterations (``iterations``, or ``init_iterations`` in a call where it is
    # initialised or moved), whatever the rest of the batch does: a batch element computes
    # exactly what the same records give with batch shape () (simulator = planner node).
    k = config.huber_k
    ml = config.range_cost == "ml"
    run = bool(np.any(active)) and K > 0
    n_short = config.iterations
    n_long = max(config.iterations, config.init_iterations)
    # Loss schedule (config.loss == "tukey"): Tukey's biweight for settled elements; after a
    # PL initialisation, Huber for the first half of the iterations, then Tukey; for a
    # suspect or moved element, Huber for the whole call (Tukey's cost is flat far from the
    # data, Huber's still points back to it).
    tukey = config.loss == "tukey"
    c = config.tukey_c
    init_before = state.initialised

    def redescend(it: int, fresh: BoolArray, before: BoolArray, n_el: NDArray[np.int64]) -> bool | BoolArray:
        if not tukey:
            return False
        if not np.any(fresh):
            return True
        return ~fresh | ((2 * it >= n_el) & ~before)

    n_elem = np.where(long_run, n_long, n_short)
    ev = _evaluate(
        x,
        rows,
        channel,
        k,
        ml,
        gate=gate,
        redescend=redescend(0, fresh_start, init_before, n_elem),
        tukey_c=c,
        suspect_sigma=config.suspect_sigma,
    )
    rows = rows.with_weights(ev.ar, ev.aa, ev.ae)
    if run:
        mu = np.full(bshape, config.lm_damping)
        x, mu, ev, g, H, F, x_lin = _lm_iterations(
            x,
            mu,
            rows,
            ev,
            prior_info,
            prior_vec,
            active,
            range(n_short),
            lambda it: redescend(it, fresh_start, init_before, n_elem),
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
                prior_info[sel],
                prior_vec[sel],
                np.ones(ne.shape, dtype=bool),
                range(n_short, n_long),
                lambda it: redescend(it, fs, ib, ne),
                channel,
                config,
            )
            x, g, H, F, x_lin = (_scatter(a, b, sel) for a, b in ((x, xs), (g, gs), (H, Hs), (F, Fs), (x_lin, xls)))
            ev = _Eval(**{f: _scatter(getattr(ev, f), getattr(evs, f), sel) for f in _Eval.__dataclass_fields__})
    else:
        x_lin = x
        g, H, F = _accumulate(ev)
        g = g + np.einsum("...ij,...j->...i", prior_info, x) - prior_vec
        H = H + prior_info
    prior_info_used, prior_vec_used = prior_info, prior_vec
    # Information of everything used, linearised at x_lin (the last iterate evaluated).
    fisher = F + prior_fisher
    suspect = active & np.any((ev.n_used >= 2.5) & (ev.n_big > config.suspect_fraction * ev.n_used), axis=-1)
    # Marginalise the rows leaving the window (the oldest n_leave), linearised at x_lin:
    # their cost ≈ ½ xᵀH_l x − (H_l x_lin − g_l)ᵀx + const.
    if n_leave > 0:
        if n_leave == K:
            gl = g - (np.einsum("...ij,...j->...i", prior_info, x_lin) - prior_vec)
            Hl = H - prior_info
            Fl = F
        else:
            gl, Hl, Fl = _accumulate(ev, slice(0, n_leave))
        add_vec = np.einsum("...ij,...j->...i", Hl, x_lin) - gl
        prior_fisher = np.where(active[..., None, None], prior_fisher + Fl, prior_fisher)
        prior_info = np.where(active[..., None, None], prior_info + Hl, prior_info)
        prior_vec = np.where(active[..., None], prior_vec + add_vec, prior_vec)
        if W > 0 and np.any(~active):
            # Before initialisation the leaving rows are kept as PL equations only.
            leave = _rows(allm, weight, channel, config).sliced(slice(0, n_leave)).subset(~active)
            A_l, b_l = _pl_rows(leave, _distance_scale(leave, config), channel)
            dr_A = dr_A.copy()
            dr_b = dr_b.copy()
            dr_A[~active] += A_l
            dr_b[~active] += b_l

    # Consistency (score) test of the recent records against the estimate.
    score_H, score_v, consistency = state.score_matrix, state.score_vector, state.consistency
    if config.consistency_threshold is not None and M > 0 and run:
        if W == 0:
            g_new = g - (np.einsum("...ij,...j->...i", prior_info_used, x_lin) - prior_vec_used)
            H_new = H - prior_info_used
        else:
            g_new, H_new, _ = _accumulate(ev, slice(K - M, K))
        score_H, score_v, consistency, fail = _score_test(
            state.score_matrix, state.score_vector, g_new, H_new, x_lin, x, active, config.consistency_threshold, config
        )
        if np.any(fail):
            suspect = suspect | fail
            fisher = np.where(fail[..., None, None], fisher * config.suspect_deflation, fisher)
    fisher = 0.5 * (fisher + np.swapaxes(fisher, -1, -2))
    finite = np.all(np.isfinite(x), axis=-1) & np.all(np.isfinite(fisher), axis=(-1, -2))
    x = np.where(finite[..., None], x, x_prev)
    info = np.where((active & finite)[..., None, None], fisher, 0.0)
    observable = active & finite & (_normalised_det(info) >= config.min_rcond)

    # The new ranges join the range window; the oldest rows leave it and join the re-check's
    # squared-range summary, weighted at this call's estimate (a record's weight 1/(4D²σ_r²(D))
    # ∝ D⁻⁴ is frozen when it joins: a window of later estimates, not the first poor ones).
    if M > 0:
        P = config.recheck_window_rows
        new_ranges = Measurements(new.positions_m, new.range_m, np.full(new.range_m.shape, np.nan), np.full(new.range_m.shape, np.nan), new.los)
        new_weight = np.where(new_row_ok & np.isfinite(new.range_m), 1.0, 0.0)
        if P > 0:
            pool = _concat(state.range_window, new_ranges)
            pool_weight = np.concatenate((range_weight, new_weight), axis=-1)
            # Valid rows at the end, oldest first (stable sort): the first M rows leave.
            order = np.argsort(pool_weight > 0.0, axis=-1, kind="stable")
            pool = _take(pool, order)
            pool_weight = np.take_along_axis(pool_weight, order, axis=-1)
            leaving = Measurements(
                pool.positions_m[..., :M, :], pool.range_m[..., :M], pool.azimuth_rad[..., :M], pool.elevation_rad[..., :M], pool.los[..., :M]
            )
            leaving_weight = pool_weight[..., :M]
            range_window = Measurements(
                pool.positions_m[..., M:, :], pool.range_m[..., M:], pool.azimuth_rad[..., M:], pool.elevation_rad[..., M:], pool.los[..., M:]
            )
            range_weight = pool_weight[..., M:]
        else:
            leaving, leaving_weight = new_ranges, new_weight
            range_window = state.range_window
        lrows = _rows(leaving, leaving_weight, channel, config)
        if np.any(lrows.ar > 0.0):
            A_r, b_r = _pl_range_rows(lrows, _range_scale(x, initialised, lrows, config), channel.gamma)
            pr_A = pr_A + A_r
            pr_b = pr_b + b_r
    else:
        range_window = state.range_window
    range_window_weight = range_weight

    if W > 0:
        window = Measurements(
            allm.positions_m[..., K - W :, :],
            allm.range_m[..., K - W :],
            allm.azimuth_rad[..., K - W :],
            allm.elevation_rad[..., K - W :],
            allm.los[..., K - W :],
        )
        window_weight = weight[..., K - W :]
    else:
        window, window_weight = state.window, state.window_weight
    used = (new_rows.ar > 0.0).sum(axis=-1) + (new_rows.aa > 0.0).sum(axis=-1) + (new_rows.ae > 0.0).sum(axis=-1)
    count = state.measurement_count + used
    return EstimatorState(
        estimate_m=x,
        information=info,
        observable=observable,
        initialised=initialised,
        prior_information=prior_info,
        prior_fisher=prior_fisher,
        prior_vector=prior_vec,
        pl_matrix=pl_A,
        pl_vector=pl_b,
        pl_dropped_matrix=dr_A,
        pl_dropped_vector=dr_b,
        pl_range_matrix=pr_A,
        pl_range_vector=pr_b,
        range_window=range_window,
        range_window_weight=range_window_weight,
        window=window,
        window_weight=window_weight,
        measurement_count=count,
        suspect=suspect,
        score_matrix=score_H,
        score_vector=score_v,
        consistency=consistency,
        calls=state.calls + 1,
    )
