"""One estimator update with a batch of new records (:func:`update`): initialisation,
robust refinement and safeguards, in that order (the package doc).

The arithmetic is compiled (:mod:`planner.estimator.kernels`, numba): one call of
:func:`planner.estimator.kernels.update.update_batch` updates every batch element, each on its
own, in the order of the package doc's steps: forgetting, the raw window, the pseudo-linear
initialisation, the global re-check, the innovation gate and the robust refinement, the
marginalisation of the rows leaving the window, the score test and the windows' advance. This
module checks the records, packs them with the state (:class:`planner.estimator.state.Packed`)
and hands the components outside the fused range/bearing kernel to it
(:mod:`planner.estimator.robust`). The kernels are imported on the first update, so that a
process that never estimates does not load the compiler.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from planner.estimator.robust import extension_callback
from planner.estimator.state import EstimatorConfig, EstimatorState, Measurements, Packed, _check, initial_state
from planner.params import Channel
from planner.sensing import COMPONENTS, SensingComponent


def _check_windows(packed: Packed, config: EstimatorConfig) -> None:
    """Raise ValueError when the state was not created with ``config``'s window sizes."""
    sizes = (
        ("window has", packed.win.shape[1], "rows, config.window_rows is", config.window_rows),
        ("range memory has", packed.mem.shape[2], "cells, config.range_memory_cells is", config.range_memory_cells),
        ("range window has", packed.rwin.shape[1], "rows, config.recheck_window_rows is", config.recheck_window_rows),
    )
    for what, found, expected, value in sizes:
        if found != value:
            raise ValueError(f"EstimatorState: {what} {found} {expected} {value}")


def _extension_values(packed: Packed, new: Measurements) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
    """The extension values' names (the window's, then the new ones), the raw window with a
    column for each (NaN where a row has none) and the new records' values (E, M, X)."""
    names = tuple(dict.fromkeys((*packed.extra_names, *new.extra_values)))
    E, M = packed.fs.shape[0], new.count
    win = packed.win
    if len(names) > len(packed.extra_names):
        win = np.concatenate((win, np.full(win.shape[:2] + (len(names) - len(packed.extra_names),), np.nan)), axis=-1)
    values = np.full((E, M, len(names)), np.nan)
    for j, name in enumerate(names):
        if name in new.extra_values:
            values[..., j] = new.extra_values[name].reshape(E, M)
    return names, win, values


def update(
    state: EstimatorState,
    measurements: Measurements,
    channel: Channel,
    config: EstimatorConfig | None = None,
    components: Sequence[SensingComponent] = COMPONENTS,
    *,
    overwrite: bool = False,
) -> EstimatorState:
    """Incorporate new records and return the new state (pure function, inputs untouched,
    unless ``overwrite``).

    Args:
        state: previous state, batch shape ``B`` (``()`` for one planner).
        measurements: new records, ``positions_m`` of shape ``B + (M, 3)`` (m, ENU), angles in
            radians, NaN for absent values, ``los`` bool ``B + (M,)``. M may be 0.
        channel: the RSS channel (γ, σ_sh/γ LOS/NLOS, σ_b), eqs. (3)-(5).
        config: estimator configuration; must be the one ``state`` was created with.
        components: the measurement components (:data:`planner.sensing.COMPONENTS`): those
            other than range and bearing whose values ``measurements.extra_values`` carries
            join the robust refinement (not the pseudo-linear initialisation).
        overwrite: the caller will not use ``state`` again: the new state is written into its
            arrays (no allocation, no copy of the range memory; for a loop that replaces its
            state at every call, e.g. the simulator's). ``state`` then holds the new values.

    Returns:
        The updated :class:`EstimatorState`; see the module docstring for the method.

    Raises:
        ValueError: shapes or dtypes that do not match the state.
    """
    from planner.estimator.kernels.update import update_batch  # the compiler, on first use

    config = EstimatorConfig() if config is None else config
    packed = state.packed()
    _check_windows(packed, config)
    new = _check(measurements, packed.batch_shape)
    E, M = packed.fs.shape[0], new.count
    names, win, values = _extension_values(packed, new)
    used, callback, errors = extension_callback(components, names, channel)
    records = (new.positions_m.reshape(E, M, 3), new.range_m.reshape(E, M), new.azimuth_rad.reshape(E, M), new.elevation_rad.reshape(E, M))
    due = config.recheck_every > 0 and M > 0 and (state.calls + 1) % config.recheck_every == 0
    ch = (channel.gamma, channel.sigma_r0_los, channel.sigma_r0_nlos, channel.sigma_bearing_rad)
    out = update_batch(
        (packed.fs, packed.ist, packed.rwin, win, packed.mem),
        (*(np.ascontiguousarray(a) for a in records), np.ascontiguousarray(new.los.reshape(E, M)), values),
        config.kernel_parameters,
        ch,
        due,
        used,
        callback.address,
        overwrite,
    )
    if errors:
        raise errors[0]
    fs, ist, rwin, win_out, mem = out
    return EstimatorState.of_packed(Packed(fs, ist, rwin, win_out, mem, packed.batch_shape, names), state.calls + 1)


def warm_up(config: EstimatorConfig | None = None) -> None:
    """Load the compiled kernels (compile them if numba's cache has none: the first update
    after installation) with one update of one record, so that a real-time process (a planner
    node) pays it at start-up, not at its first step."""
    config = EstimatorConfig() if config is None else config
    nan = np.full(1, np.nan)
    update(initial_state((), config), Measurements(np.zeros((1, 3)), np.ones(1), nan, nan, np.ones(1, dtype=bool)), Channel(), config)


__all__ = ["update", "warm_up"]
