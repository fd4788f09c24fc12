"""Real radio: the received-power model behind the paper's ranging, fitted to and localized from logs.

* :mod:`planner.radio.tobit`: the censored normal model of a power sample (undetected samples
  are censored, not measurements).
* :mod:`planner.radio.pathloss`: the log-distance model, antenna patterns, the channel fitted
  to a calibration log, the residual's correlation distance.
* :mod:`planner.radio.localize`: an emitter's position from a log, with unknown transmit power,
  censored samples, its 95 % confidence region, its PEB and a verdict when the log cannot
  localize it.
* :mod:`planner.radio.unknown_power`: the paper's ranging Fisher information with the source's
  power as a nuisance parameter (4 × 4, its Schur complement, the A/D costs and gradients) and
  the joint estimator of position and power offset.

Pure numpy/scipy (part of the math core).
"""
