"""The argument types of the entry kernels built ahead of time (:mod:`planner.aot`), as
expressions of ``numba.core.types``. Written by :func:`missions.study.kernel_signatures.record`; do not edit by hand.
"""

SIGNATURES: dict[str, str] = {
    "plan_batch": "none(Tuple((Array(int64, 1, 'C'), Array(float64, 2, 'C'), Array(float64, 1, 'C'), Array(boolean, 1, 'C'), Array(float64, 3, 'C'), Array(boolean, 2, 'C'), Array(int64, 2, 'C'), Array(int64, 2, 'C'), Array(boolean, 2, 'C'), Array(float64, 2, 'C'), Array(float64, 3, 'C'), Array(boolean, 1, 'C'), Array(float64, 2, 'C'), )), Array(boolean, 2, 'C'), Tuple((Array(boolean, 1, 'C'), Array(boolean, 1, 'C'), boolean, )), Tuple((Array(float64, 2, 'C'), Array(float64, 2, 'C'), Array(boolean, 2, 'C'), Array(boolean, 1, 'C'), Array(float64, 2, 'C'), Array(float64, 1, 'C'), Array(float64, 3, 'C'), Array(int64, 2, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), Array(int64, 2, 'C'), )), Tuple((int64, Array(float64, 2, 'C'), boolean, boolean, boolean, boolean, Array(float64, 2, 'C'), Array(float64, 2, 'C'), Array(float64, 1, 'C'), Array(float64, 1, 'C'), float64, float64, )), Tuple((Array(float64, 2, 'C'), Array(float64, 2, 'C'), Array(boolean, 2, 'C'), Array(boolean, 1, 'C'), Array(float64, 2, 'C'), Array(float64, 1, 'C'), Array(float64, 3, 'C'), Array(int64, 2, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), Array(int64, 2, 'C'), )), Tuple((Array(float64, 2, 'C'), Array(boolean, 2, 'C'), Array(float64, 2, 'C'), )), Tuple((Array(float64, 1, 'C'), Array(float64, 2, 'C'), Array(int8, 1, 'C'), )), boolean)",
    "policy_batch": "signature(Array(float64, 2, 'C'), Array(float64, 1, 'C'), Array(boolean, 1, 'C'), Array(float64, 1, 'C'), Array(float64, 1, 'C'), Array(float64, 1, 'C'), Array(boolean, 1, 'C'), float64, Array(float64, 1, 'C'))",
    "small_batch": "signature(Tuple((Array(float64, 1, 'C'), Array(float64, 2, 'C'), )), Array(float64, 3, 'C'), Array(float64, 2, 'C'))",
    "distances_batch": "signature(Tuple((Array(float64, 1, 'C'), Array(float64, 2, 'C'), )), Array(float64, 2, 'C'), Array(float64, 2, 'C'), Array(float64, 2, 'C'), boolean)",
    "fim_batch": "none(Array(float64, 2, 'C'), Array(float64, 3, 'C'), Array(boolean, 2, 'C'), Array(boolean, 2, 'C'), Array(float64, 2, 'C'), Array(float64, 1, 'C'), Array(float64, 3, 'C'))",
    "invert_batch": "none(Array(float64, 3, 'C'), Array(float64, 3, 'C'), Array(float64, 2, 'C'))",
    "update_batch": "signature(Tuple((Array(float64, 2, 'C'), Array(int64, 2, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), )), Tuple((Array(float64, 2, 'C'), Array(int64, 2, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), )), Tuple((Array(float64, 3, 'C'), Array(float64, 2, 'C'), Array(float64, 2, 'C'), Array(float64, 2, 'C'), Array(boolean, 2, 'C'), Array(float64, 3, 'C'), )), Array(float64, 1, 'C', readonly=True), UniTuple(float64, 4), boolean, Array(boolean, 1, 'C'), int64, boolean)",
    "line_of_sight": "none(Array(float64, 2, 'C'), Array(float64, 1, 'C'), Array(float64, 2, 'C'), Array(float64, 2, 'C'), Array(boolean, 1, 'C'))",
    "hop_counts": "none(Array(float64, 3, 'C'), float64, int64, Array(boolean, 2, 'C'), boolean, Array(int64, 3, 'C'))",
    "update_saved_steps": "none(Array(int64, 3, 'C'), Array(int64, 3, 'C'), int64, int64)",
    "gather_view": "none(Array(float64, 4, 'C'), Array(boolean, 3, 'C'), Array(int64, 3, 'C'), int64, Array(float64, 4, 'C'), Array(boolean, 3, 'C'), Array(boolean, 3, 'C'), Array(int16, 3, 'C'))",
    "gather_new_records": "none(Array(int64, 3, 'C'), Array(int64, 3, 'C'), Array(float64, 4, 'C'), Array(boolean, 3, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), Array(float64, 4, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), Array(float64, 3, 'C'), Array(boolean, 3, 'C'))",
    "nearest_peer_distance": "none(Array(float64, 4, 'C'), Array(float64, 3, 'C'))",
    "same_views": "none(Array(int64, 3, 'C'), Array(int64, 2, 'C'))",
    "position_error_bounds": "none(Array(float64, 3, 'C'), Array(float64, 1, 'C'), Array(boolean, 1, 'C'))",
}
