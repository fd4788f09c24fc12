"""Where each quantity of the estimator's state lives in the packed arrays the compiled kernels
take (:mod:`planner.estimator.kernels`). Plain integers, no compiler import: the state module
packs and unpacks with them, the kernels index with them.

A batch element's state is five arrays (leading batch axis flattened to E elements):

* ``fs`` (E, :data:`NF`) float64: estimate, information, prior (Λ, F, η), the three
  pseudo-linear systems (A, b), the recent-records score (S_H, S_v) and its statistic T;
* ``ist`` (E, :data:`NI`) int64: observable, initialised, angles used, suspect, measurement count;
* ``rwin`` (E, R, :data:`NRW`) float64: the range window (position m ENU, range m, LOS 0/1,
  weight);
* ``win`` (E, W, :data:`NW` + X) float64: the raw window (position, range, azimuth, elevation,
  LOS 0/1, weight, then the X extension values);
* ``mem`` (E, :data:`NM`, C) float64: the range memory, one row per quantity, one column per
  cell: the sums (Σwp, n, S1, S2, σ_r0, T, Q), then what an evaluation reads (centre, σ_r0²,
  lever, spread, ‖centre‖², n, S1, S2; zeros for an empty cell), see
  :mod:`planner.estimator.kernels.memory`.
"""

from __future__ import annotations

# fs: fixed-size float fields (offset, size)
F_EST, F_INFO, F_PINFO, F_PFISH, F_PVEC = 0, 3, 12, 21, 30
F_PLA, F_PLB, F_DRA, F_DRB, F_PRA, F_PRB = 33, 49, 53, 69, 73, 89
F_SH, F_SV, F_CONS = 93, 102, 105
NF = 106

# ist: flags and counts
I_OBS, I_INIT, I_ANG, I_SUSP, I_COUNT = 0, 1, 2, 3, 4
NI = 5

# rwin: range window rows
RW_X, RW_R, RW_LOS, RW_W = 0, 3, 4, 5
NRW = 6

# win: raw window rows (the kernels' merged rows use the same columns)
W_X, W_R, W_AZ, W_EL, W_LOS, W_W = 0, 3, 4, 5, 6, 7
NW = 8

# mem: range memory rows (sums, then the evaluation rows)
M_PS, M_N, M_S1, M_S2, M_S0, M_T, M_Q = 0, 3, 4, 5, 6, 7, 10
M_CX, M_S0SQ, M_L, M_SP, M_CC, M_EN, M_ES1, M_ES2 = 11, 14, 15, 18, 19, 20, 21, 22
NM_SUMS = 11
NM = 23

# The configuration and channel as one float64 vector (EstimatorConfig.kernel_parameters).
P_WINDOW, P_LAMBDA, P_HUBER, P_TUKEY, P_TUKEY_C, P_GATE, P_GATE_FRAC = 0, 1, 2, 3, 4, 5, 6
P_ITER, P_INIT_ITER, P_SUSP_SIGMA, P_SUSP_FRAC, P_SUSP_DEFL = 7, 8, 9, 10, 11
P_RECHECK_THR, P_RECHECK_TRUST, P_RWINDOW, P_CELLS, P_RADIUS, P_LL_DROP = 12, 13, 14, 15, 16, 17
P_CONS_THR, P_CONS_LAMBDA, P_LM_DAMP, P_NLOS_BW, P_MIN_RCOND, P_PL_RCOND = 18, 19, 20, 21, 22, 23
P_INIT_D, P_INIT_REL, P_MIRROR_BELOW, P_ML, P_LO, P_HI = 24, 25, 26, 27, 28, 31
P_GAMMA, P_S0_LOS, P_S0_NLOS, P_SB = 34, 35, 36, 37
NP = 38
