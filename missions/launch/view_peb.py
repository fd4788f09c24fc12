"""The position error bound of one drone's view, as the launcher computes it from the records it
heard: the PEB of the Fisher information of the records the view names, at the true source."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from comms.messages import Record
from planner.agent import records_as_arrays
from planner.config import PlannerConfig
from planner.fim import fisher_information, position_error_bound
from planner.radio.unknown_power import fisher_information_unknown_power, position_error_bound_unknown_power


def peb_of_view(config: PlannerConfig, saved: Sequence[int], recs: dict[tuple[int, int], Record], src: np.ndarray, true_offset: float = 0.0) -> float:
    """The PEB (m) of a view.

    Args:
        config: the mission's planner config (sensing masks and channel).
        saved: the view's step of each drone's record (index j: drone j + 1; −1: none).
        recs: records by (step, drone id); a view's record missing here counts as none.
        src: the source position, shape (3,), m ENU.
        true_offset: the source's power offset b (:mod:`planner.radio.power_offset`); with the
            power unknown (``config.unknown_power``) the PEB is that of the position's
            information with b unknown (the Schur complement).
    """
    pos, valid, los = records_as_arrays([recs.get((s, j + 1)) if s >= 0 else None for j, s in enumerate(saved)])
    extra = {name: mask & valid for name, mask in config.extra_masks.items()}
    if config.unknown_power is None and true_offset == 0.0:
        J = fisher_information(src, pos, config.ranging & valid, config.bearing & valid, los, config.channel, extra)
        return float(position_error_bound(J)[0])
    J4 = fisher_information_unknown_power(src, pos, config.ranging & valid, config.bearing & valid, los, config.channel, true_offset, extra)
    if config.unknown_power is not None:
        return float(position_error_bound_unknown_power(J4)[0])
    return float(position_error_bound(J4[:3, :3])[0])
