r"""Robust, recursive, batched maximum-likelihood estimator of the source position.

The paper (Guerra, Dardari, Djurić) takes the source estimate p̂0 as given (sec. II-B,
footnote 2); fimnav computes it here from the ranging and bearing estimates of eq. (3), each
tagged with the position it was taken at and its LOS/NLOS flag. Design notes, the bias
discussion and the measured figures are in ``docs/estimator.md``.

Public API
----------
``Measurements``
    One batch of records. ``positions_m`` (..., M, 3) m ENU; ``range_m``, ``azimuth_rad``,
    ``elevation_rad`` (..., M); ``los`` (..., M) bool. NaN marks an absent value; a row whose
    position is NaN is no measurement, so batch elements may carry different counts.
``EstimatorConfig``
    Frozen tuning: raw window, forgetting, robust loss, iterations, safeguards, ...
``EstimatorState``
    Frozen state: ``estimate_m`` (..., 3), ``information`` (..., 3, 3) (Fisher information of
    everything used, at the estimate, robust weights applied), ``observable`` (...,) bool,
    ``initialised`` (...,) bool, plus the internal accumulators.
``initial_state(batch_shape, config) -> EstimatorState``
``update(state, measurements, channel, config) -> EstimatorState``  (pure)
``empty_measurements(batch_shape, rows) -> Measurements``  (all NaN)
``warm_up(config)``  (load, or compile, the kernels before a real-time loop)

Measurement model (paper eqs. 3-5), drone at p, source at p0, r = p0 - p:

.. math::
    d = \lVert r\rVert,\quad \phi = \operatorname{atan2}(r_y, r_x),\quad
    \theta = \operatorname{atan2}(r_z, \sqrt{r_x^2+r_y^2})

    \hat d = d + n_r,\ n_r\sim\mathcal N(0, \sigma_{r,0}^2 d^{\gamma}),\qquad
    \hat\phi = \phi + n_b,\ \hat\theta = \theta + n_b,\ n_b\sim\mathcal N(0,\sigma_b^2)
    \text{ (LOS)}

with σ_r0 = (ln10/10)(σ_sh/γ) for the link's LOS or NLOS ratio; an NLOS bearing is the
outlier ω of eq. (3) and is given weight ``config.nlos_bearing_weight`` (0 by default).

Method, per call of :func:`update` and per batch element (vectorised over both):

1. Closed-form initialisation: pseudo-linear (PL) normal equations, linear in
   θ = (p0, R = ‖p0‖²), accumulated exactly until the element is initialised. Bearings
   project p0 − p onto the two directions orthogonal to the measured unit vector u
   (Lingren & Gong, IEEE T-AES 14(4), 1978; 3-D form of Doğançay, IEEE TSP 63(1), 2015); a
   range with a usable bearing gives uᵀ(p0 − p) = d̂; a range alone gives the squared-range
   equation 2pᵀp0 − R = ‖p‖² − d̂² + σ_r² (unconstrained LS of Cheung, So, Ma & Chan, IEEE
   TSP 52(4), 2004, bias E[d̂²] = d² + σ_r² removed), with the constraint R = ‖p0‖² applied
   along the weakest direction (coplanar drones: mirror ambiguity, ``config.mirror``).
2. Robust ML refinement, Levenberg-Marquardt with Fisher scoring, warm-started, of

   .. math::
       C(p_0) = \tfrac12 p_0^T\Lambda p_0 - \eta^T p_0 + \sum_i a_i\,\rho(e_i),
       \qquad e_i = (z_i - h_i(p_0))/\sigma_i

   over the latest ``window_rows`` raw records plus the new ones; (Λ, η) is the
   information-form summary of the records that left the window (each marginalised,
   linearised at the last iterate of the call it left). σ_r² = σ_r0² d^γ at the iterate
   ("gls") or with ½ ln σ_r² in the cost ("ml"); the reported Fisher information includes
   ∇σ²∇σ²ᵀ/(2σ⁴) = γ²/(2d²)∇d∇dᵀ (eq. 12's A_d). ρ: Huber from a fresh start, then Tukey's
   biweight (no influence beyond ``tukey_c``σ); steps capped at half the mean range.
3. Safeguards against a frozen wrong linearisation: *suspect* elements (too many records far
   from the estimate) get a deflated prior and Huber iterations; every ``recheck_every``
   calls the squared-range PL solution of all past ranges (each weighted at the estimate of
   the call it leaves a raw range window, ``recheck_window_rows``) replaces the estimate when it is
   much better on the PL cost and on the new records, claiming only ``recheck_trust`` of that
   solution's information (it can be biased by tens of metres). With the range memory
   (``range_memory_cells``, :mod:`planner.estimator.memory`; a mission's default for a static
   source), an element that has used
   only ranges is re-checked on the exact likelihood of every range so far instead, and its
   prior re-linearised at the likelier optimum. Optional innovation gate;
   a score test of the recent records against the estimate (``consistency_threshold``).
4. Forgetting λ ∈ (0, 1]: every stored contribution (Λ, η, PL equations, window weights)
   is multiplied by λ per call, for a moving source.
5. Observability: initialised and det J/(tr J/3)³ ≥ ``min_rcond`` (J the information).

Every batch element runs its own number of LM iterations (``iterations``, or
``init_iterations`` in the call where it is initialised or moved), so an element of a batch
computes what the same records give with batch shape () (the simulator, batch (trials,
drones), and a planner node, batch (), agree).

The arithmetic is compiled (numba; :mod:`planner.estimator.kernels`, imported on the first
update, cached on disk): one call updates every batch element in one compiled loop.

Per-call cost is O(batch × (window_rows + M)), independent of the number of calls. No NaN is
returned: the estimate is finite everywhere (the origin, or the last value, until the element
is initialised), and ``observable`` says when it can be trusted.
"""

from __future__ import annotations

from planner.estimator.state import EstimatorConfig, EstimatorState, Measurements, empty_measurements, initial_state
from planner.estimator.update import update, warm_up

__all__ = ["EstimatorConfig", "EstimatorState", "Measurements", "empty_measurements", "initial_state", "update", "warm_up"]
