"""The settings of the source estimator with the transmit power unknown
(:mod:`planner.radio.power_estimator`), held by :class:`planner.config.PlannerConfig`."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class UnknownPowerSettings:
    """Tuning of the joint estimator (module doc; counts are rows and calls).

    Attributes:
        window_rows: raw records kept per element before they are marginalised.
        iterations: scoring iterations per call; init_iterations: at initialisation.
        recheck_every: calls between two second starts from the known-power estimate (0: none).
        recheck_nll_drop: negative log-likelihood drop that moves the estimate to the second start.
        offset_prior_sigma_db: σ of the weak zero-mean prior on the power offset, dB.
        min_ranges: ranges in the window before the joint estimate starts.
        max_halvings: step halvings per scoring iteration.
        range_cells: cells of ranges that left the window, kept by where they were taken (their
            exact likelihood up to the spread within a cell: a linearised prior cannot hold the
            curved likelihood of the height of a source seen from drones nearly level with it);
            once every cell is taken, a range no cell is near joins the linearised prior (by
            then the estimate has settled).
        cell_radius: a range joins a cell of its LOS class within this fraction of the cell's
            mean range.
    """

    window_rows: int = 500
    iterations: int = 1
    init_iterations: int = 25
    recheck_every: int = 5
    recheck_nll_drop: float = 1.0
    offset_prior_sigma_db: float = 20.0
    min_ranges: int = 5
    max_halvings: int = 8
    range_cells: int = 256
    cell_radius: float = 0.05

    def __post_init__(self) -> None:
        for name in ("window_rows", "iterations", "init_iterations", "min_ranges", "max_halvings", "range_cells"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"UnknownPowerSettings.{name}: expected an integer >= 1, found {v!r}")
        if not (isinstance(self.recheck_every, int) and self.recheck_every >= 0):
            raise ValueError(f"UnknownPowerSettings.recheck_every: expected an integer >= 0, found {self.recheck_every!r}")
        if not self.offset_prior_sigma_db > 0.0:
            raise ValueError(f"UnknownPowerSettings.offset_prior_sigma_db: expected > 0, found {self.offset_prior_sigma_db!r}")


__all__ = ["UnknownPowerSettings"]
