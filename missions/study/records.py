"""What a Monte Carlo run is and what it gives, without the simulator: :class:`RunSpec`,
:class:`SimulationResult`, the fault-free reference :class:`PenaltyReference` and the PEB
penalty of injected faults against a fault-free run (:func:`fault_penalty_against`).

A process that only submits runs and writes their results (the client of ``fimnav montecarlo
--cluster``, whose chunks run on Dask workers) imports this module, not the simulator
(:mod:`missions.study.simulator`) and its compiled kernels: it never loads numba.
"""

from __future__ import annotations

import dataclasses
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from missions.format.schema import Faults, Mission
from planner.params import Criterion

FloatArray = NDArray[np.float64]

#: Constraint families of the safety accounting, in summary order.
SAFETY_FAMILIES: tuple[str, ...] = ("uav", "source", "obstacle", "altitude", "speed", "turn_rate")

#: Tolerance of the kinematic accounting (floating point of the polar round trip), m and rad.
KINEMATIC_TOL: float = 1e-9
#: The same for positions reported over MAVLink (m): float32 resolves ~1.5e-5 m at 150 m
#: from the origin, and a step length or direction comes from two such positions.
MAVLINK_KINEMATIC_TOL: float = 1e-4


@dataclass(frozen=True)
class RunSpec:
    """What to run: a mission with its per-run overrides."""

    mission: Mission
    criterion: Criterion
    trials: int
    steps: int
    #: Index of the first trial: the run is trials ``first_trial`` … ``first_trial + trials − 1``
    #: of the mission's seed. Trial m's noise, faults and perturbations depend on (seed, m,
    #: drone) only, so one trial of a larger run replays alone (``first_trial=99, trials=1``):
    #: bit-identical without injected faults. With them the faults drawn are the same, but some
    #: batched sums then run over arrays of another shape: the positions agree to rounding at
    #: first, and the chaotic runs can part after tens of steps.
    first_trial: int = 0

    @property
    def label(self) -> str:
        """``<mission id> (A)``: the name of the run in tables and legends."""
        return f"{self.mission.id} ({self.criterion})"


@dataclass(frozen=True)
class SimulationResult:
    """Records of a Monte Carlo run. Step axis first; k = 0 is the start.

    Attributes:
        spec: what was run.
        positions_m: true positions, (K+1, M, N, 3), m, ENU.
        estimates_m: each drone's source estimate at step k, (K, M, N, 3).
        estimate_error_m: |p̂_0,i − p0|, (K, M, N), m.
        observable: estimator says observable, (K, M, N) bool.
        peb_m: PEB of eq. 18 per drone view, (K, M, N), m; +inf where J is singular.
        source_m: true source position per step, (K+1, 3).
        margins_m: per family, the worst margin of each drone at each step, (K, M, N): distance
            minus its safety distance for uav/source/obstacle, distance to the altitude box for
            altitude, and for speed and turn_rate the slack to the limit (m and rad).
        active: counts of steps where each control constraint family was active (uav, source,
            obstacle, altitude), summed over drones and trials, (K, 4).
        singular_fallback: (K, M, N) bool, the drone used the singular-FIM fallback.
        filtered: (K, M, N) bool, the safety filter replaced the step.
        loiter: (K, M, N) bool, the drone loitered: its own ranges put the source within reach
            and its estimate gave no direction to trust (:func:`planner.agent.must_loiter`).
        record_ages: age k − ℓ of every record drone i held of peer j, (K, M, N, N); −1 if none.
        runtime_s: wall time of the run (s).
        power_offset_db: with the source's power unknown (``source.power: unknown``), each
            drone's estimate of the source's power above the nominal one, (K, M, N), dB (NaN:
            not estimated yet, or no drone of its view ranges); None with the power known.
    """

    spec: RunSpec
    positions_m: FloatArray
    estimates_m: FloatArray
    estimate_error_m: FloatArray
    observable: NDArray[np.bool_]
    peb_m: FloatArray
    source_m: FloatArray
    margins_m: dict[str, FloatArray]
    active: NDArray[np.int64]
    singular_fallback: NDArray[np.bool_]
    filtered: NDArray[np.bool_]
    loiter: NDArray[np.bool_]
    record_ages: NDArray[np.int16]
    runtime_s: float
    extra: dict[str, float] = field(default_factory=dict)
    power_offset_db: FloatArray | None = None

    def violations(self) -> dict[str, int]:
        """Number of (step, trial, drone) with a negative margin, per safety family."""
        return {name: int((m < 0.0).sum()) for name, m in self.margins_m.items()}

    def peb_stats(self) -> dict[str, FloatArray]:
        """Per step: mean PEB over drones and trials (eq. 18, singular views excluded), its 10th
        and 90th percentiles (singular views count as +inf), and the singular fraction."""
        peb = self.peb_m.reshape(self.peb_m.shape[0], -1)
        count = np.isfinite(peb).sum(-1)
        return {
            "mean": _step_means(self.peb_m),
            "p10": np.percentile(peb, 10, axis=-1, method="nearest"),
            "p90": np.percentile(peb, 90, axis=-1, method="nearest"),
            "singular_fraction": 1.0 - count / peb.shape[1],
        }


def without_faults(mission: Mission) -> Mission:
    """The same mission with ``comms.faults`` off (the baseline of the PEB penalty)."""
    return mission.model_copy(update={"comms": mission.comms.model_copy(update={"faults": Faults()})})


def mean_record_age(result: SimulationResult) -> float:
    """Mean age k − ℓ (steps) of the peers' records the drones held, over steps, trials and
    drone pairs i ≠ j that held one (ages grow when the memory buffer falls back)."""
    ages = result.record_ages
    n = ages.shape[-1]
    held = (ages >= 0) & ~np.eye(n, dtype=bool)
    return float(ages[held].mean()) if held.any() else float("nan")


@dataclass(frozen=True)
class PenaltyReference:
    """What :func:`fault_penalty_against` takes from a fault-free run: enough to compare a run with
    injected faults against it without simulating it again (``fimnav montecarlo --baselines``).

    Attributes:
        mission_json: the fault-free mission as run (pydantic JSON): a run with faults matches
            it when ``without_faults`` of its mission gives the same text.
        criterion, trials, steps, first_trial: the run's :class:`RunSpec` (criterion "A"/"D").
        oracle_estimate, float32_positions: the simulation's flags (a distributed run counts as
            float32 positions).
        peb_mean_m: per step, the mean PEB (eq. 18) over drones and trials (singular views
            skipped), (K,), m.
        final_trial_means_m: per trial, the mean final PEB over drones, (M,), m.
        trial_means_m: per trial, the mean over steps of the mean PEB over drones, (M,), m.
        mean_record_age_steps: :func:`mean_record_age`, steps.
        runtime_s: the run's wall time, s.
    """

    mission_json: str
    criterion: str
    trials: int
    steps: int
    first_trial: int
    oracle_estimate: bool
    float32_positions: bool
    peb_mean_m: FloatArray
    final_trial_means_m: FloatArray
    trial_means_m: FloatArray
    mean_record_age_steps: float
    runtime_s: float

    @classmethod
    def of(cls, result: SimulationResult, steps: int | None = None) -> PenaltyReference:
        """The reference of a fault-free ``result``, over its first ``steps`` steps (default all)."""
        spec = result.spec
        peb = result.peb_m if steps is None else result.peb_m[:steps]
        k = peb.shape[0]
        return cls(
            mission_json=spec.mission.model_dump_json(),
            criterion=spec.criterion,
            trials=spec.trials,
            steps=spec.steps,
            first_trial=spec.first_trial,
            oracle_estimate=bool(result.extra.get("oracle_estimate", 0.0)),
            float32_positions=bool(result.extra.get("float32_positions", 0.0) or result.extra.get("distributed", 0.0)),
            peb_mean_m=_step_means(peb),
            final_trial_means_m=_trial_means(peb[k - 1 : k]),
            trial_means_m=_trial_means(peb),
            mean_record_age_steps=mean_record_age(result),
            runtime_s=float(result.runtime_s),
        )

    def matches(self, spec: RunSpec, oracle_estimate: bool) -> bool:
        """True when this is the fault-free reference of ``spec`` (a run with faults, planned
        with the true source if ``oracle_estimate``): the same mission without faults, the same
        criterion, trials, steps and first trial, the same flags (float32 positions off)."""
        return (
            self.mission_json == without_faults(spec.mission).model_dump_json()
            and (self.criterion, self.trials, self.steps, self.first_trial) == (spec.criterion, spec.trials, spec.steps, spec.first_trial)
            and (self.oracle_estimate, self.float32_positions) == (oracle_estimate, False)
        )

    def save(self, path: Path) -> None:
        """Write to ``path`` (numpy ``.npz``, float64 exact)."""
        arrays: dict[str, Any] = {f.name: np.asarray(getattr(self, f.name)) for f in dataclasses.fields(self)}
        with path.open("wb") as fh:
            np.savez_compressed(fh, **arrays)

    @classmethod
    def load(cls, path: Path) -> PenaltyReference:
        """Read what :meth:`save` wrote; ValueError naming the file if it is not such a file."""
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
            kwargs: dict[str, object] = {}
            for f in dataclasses.fields(cls):
                v = data[f.name]
                kwargs[f.name] = v.astype(np.float64) if v.ndim else v.item()
            ref = cls(**kwargs)  # type: ignore[arg-type]
        except (OSError, KeyError, ValueError, TypeError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{path}: not a fault-free run's PEB reference ({type(exc).__name__}: {exc})") from None
        return ref


def fault_penalty_against(mission: Mission, result: SimulationResult, baseline: SimulationResult | PenaltyReference) -> dict[str, float | None]:
    """PEB penalty of the injected loss and delay: ``result`` (run with ``mission.comms.faults``)
    against ``baseline``, the same mission without faults (:func:`missions.study.simulator.fault_penalty`
    simulates it when it is not at hand). The PEB is eq. 18 at the true source, averaged over
    drones and trials per step (:meth:`SimulationResult.peb_stats`).

    Args:
        mission: the mission as run (with faults).
        result: its result (in-process or distributed).
        baseline: the fault-free result, or its :class:`PenaltyReference`.

    Returns:
        JSON-ready dict: the fault settings, final mean PEB (m) with and without faults, their
        difference (m), its standard error over trials (``*_se_m``, paired: the trials share
        their seeds) and ratio, the same for the mean over steps of the mean PEB, the PEB at
        step 0 with and without faults (same positions: missing records only raise it), the
        mean record age (steps) with and without faults, the fraction of peer records lost
        (in-process runs) and the baseline's run time (s). None where a PEB is undefined.
    """
    faulty = result.peb_stats()["mean"]
    if isinstance(baseline, SimulationResult):
        baseline = PenaltyReference.of(baseline, min(len(faulty), baseline.peb_m.shape[0]))
    clean = baseline.peb_mean_m
    k = min(len(faulty), len(clean))
    if len(baseline.trial_means_m) != result.peb_m.shape[1] or k != len(clean):
        raise ValueError(
            f"fault_penalty: the baseline has {len(baseline.trial_means_m)} trials × {len(clean)} steps, "
            f"the run {result.peb_m.shape[1]} × {len(faulty)}"
        )
    final_f, final_b = float(faulty[k - 1]), float(clean[k - 1])
    both = np.isfinite(faulty[:k]) & np.isfinite(clean[:k])  # steps where every view is singular are skipped
    mean_f = float(faulty[:k][both].mean()) if both.any() else float("nan")
    mean_b = float(clean[:k][both].mean()) if both.any() else float("nan")

    # Per trial (same seeds: paired, common random numbers): the spread of the penalty.
    se_final = _paired_se(_trial_means(result.peb_m[k - 1 : k]), baseline.final_trial_means_m)
    se_mean = _paired_se(_trial_means(result.peb_m[:k]), baseline.trial_means_m)
    init_f, init_b = float(faulty[0]), float(clean[0])

    def num(x: float) -> float | None:
        return x if np.isfinite(x) else None

    out: dict[str, float | None] = {
        "loss": mission.comms.faults.loss,
        "extra_delay_steps": float(mission.comms.faults.extra_delay_steps),
        "final_peb_mean_m": num(final_f),
        "baseline_final_peb_mean_m": num(final_b),
        "final_peb_penalty_m": num(final_f - final_b),
        "final_peb_penalty_ratio": num(final_f / final_b) if final_b > 0 else None,
        "mean_peb_over_steps_m": num(mean_f),
        "baseline_mean_peb_over_steps_m": num(mean_b),
        "mean_peb_penalty_m": num(mean_f - mean_b),
        "mean_peb_penalty_ratio": num(mean_f / mean_b) if mean_b > 0 else None,
        "final_peb_penalty_se_m": num(se_final),
        "mean_peb_penalty_se_m": num(se_mean),
        "initial_peb_mean_m": num(init_f),
        "baseline_initial_peb_mean_m": num(init_b),
        "initial_peb_penalty_ratio": num(init_f / init_b) if init_b > 0 else None,
        "mean_record_age_steps": num(mean_record_age(result)),
        "baseline_mean_record_age_steps": num(baseline.mean_record_age_steps),
        "baseline_runtime_s": round(baseline.runtime_s, 3),
    }
    if "fault_lost_fraction" in result.extra:
        out["lost_fraction"] = float(result.extra["fault_lost_fraction"])
    return out


def _step_means(peb_m: FloatArray) -> FloatArray:
    """Per step, the mean PEB over trials and drones (singular views skipped), from PEB
    (K, M, N); NaN at a step without a finite PEB."""
    peb = peb_m.reshape(peb_m.shape[0], -1)
    finite = np.isfinite(peb)
    count = finite.sum(-1)
    return np.divide(np.where(finite, peb, 0.0).sum(-1), count, out=np.full(peb.shape[0], np.nan), where=count > 0)


def _trial_means(peb_m: FloatArray) -> FloatArray:
    """Per trial, the mean over steps of the mean PEB over drones (singular views skipped),
    from PEB (K, M, N); NaN for a trial without a finite PEB."""
    finite = np.isfinite(peb_m)
    count = finite.sum(-1)
    per_step = np.divide(np.where(finite, peb_m, 0.0).sum(-1), count, out=np.full(count.shape, np.nan), where=count > 0)
    ok = np.isfinite(per_step)
    n = ok.sum(0)
    return np.divide(np.where(ok, per_step, 0.0).sum(0), n, out=np.full(n.shape, np.nan), where=n > 0)


def _paired_se(a: FloatArray, b: FloatArray) -> float:
    """Standard error (m) of the mean of the per-trial differences a − b (NaN below 2 trials)."""
    d = (a - b)[np.isfinite(a - b)]
    return float(d.std(ddof=1) / np.sqrt(d.size)) if d.size >= 2 else float("nan")
