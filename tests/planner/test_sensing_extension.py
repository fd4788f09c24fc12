"""A new measurement component needs no edit outside planner/sensing.py, its tests and docs.

The toy component below is defined and registered in this test only: a distance-squared
measurement s = d² + n, n ~ N(0, σ_s²) with a constant σ_s (m²), drawn from a sixth uniform
column. It is handed to the math core as ``components=COMPONENTS + (TOY,)`` with its masks in
``extra_masks``, and the Fisher information, the cost gradient, the observation and the
estimator's refinement pick it up; the registry's own results stay bit-identical. With a toy
role in a toy sensing table (``TOY_SENSING``, passed as ``sensing=``) it flies a mission in the
in-process simulator, and its records round-trip through the wire format.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import ClassVar

import numpy as np
import pytest
from numpy.typing import ArrayLike

from comms.messages import Record, decode, encode
from missions.format.loader import load_mission
from missions.format.schema import Mission
from missions.study.simulator import RunSpec, SimulationResult, simulate
from planner import Channel, cost, cost_gradient, fisher_information
from planner.agent import measurements_from_records
from planner.estimator import EstimatorConfig, EstimatorState, Measurements, initial_state, update
from planner.geometry import line_of_sight
from planner.observation import observe, observe_from_uniforms
from planner.params import Criterion
from planner.randomness import MEASUREMENT_DRAWS, MEASUREMENT_STREAM, presampled_uniforms
from planner.sensing import (
    COMPONENTS,
    ROLES,
    BoolArray,
    FloatArray,
    LinkGeometry,
    SensingComponent,
    SensingRole,
    SensingTable,
    measurement_draws,
)

CHANNEL = Channel()
SIGMA_S_M2 = 40.0


@dataclass(frozen=True)
class RangeSquaredModel(SensingComponent):
    """Toy component s = d² + n, σ_s constant (m²): ∇_{p0} s = 2r, J_s = (4/σ_s²) r rᵀ."""

    name: ClassVar[str] = "range_squared"
    wire_bit: ClassVar[int] = 4
    value_names: ClassVar[tuple[str, ...]] = ("range_squared_m2",)
    uniform_columns: ClassVar[tuple[int, ...]] = (5,)
    fim_row_count: ClassVar[int] = 1
    sigma_m2: float = SIGMA_S_M2

    def simulate_values(
        self, d: FloatArray, phi: FloatArray, theta: FloatArray, los: BoolArray, channel: Channel, uniforms: FloatArray
    ) -> tuple[FloatArray, ...]:
        from scipy.special import ndtri

        return (d * d + self.sigma_m2 * ndtri(np.clip(uniforms[..., 5], 1e-300, None)),)

    def fim_vectors(self, geom: LinkGeometry) -> FloatArray:
        return geom.r[..., None, :]

    def fim_row_weights(self, geom: LinkGeometry, mask: ArrayLike, los_w: FloatArray, channel: Channel) -> FloatArray:
        w = np.asarray(mask, dtype=bool) * (4.0 / self.sigma_m2**2) * np.ones_like(geom.d)
        return w[..., None]

    def cost_gradient_terms(
        self, geom: LinkGeometry, q: FloatArray, MV: FloatArray, mask: ArrayLike, los_w: FloatArray, channel: Channel, los_trace: bool
    ) -> tuple[FloatArray, FloatArray | None]:
        # ∂ tr(M (4/σ²) r rᵀ)/∂r = (8/σ²) M r; no LOS dependence.
        g = np.asarray(mask, dtype=bool)[..., None] * (8.0 / self.sigma_m2**2) * MV[..., 0, :]
        return g, (np.zeros(np.shape(geom.d)) if los_trace else None)

    def estimator_terms(self, values: tuple[FloatArray, ...], geom: LinkGeometry, channel: Channel) -> tuple[FloatArray, FloatArray]:
        (z,) = values
        e = (z - geom.d2) / self.sigma_m2
        de = -2.0 * geom.r / self.sigma_m2
        return e[..., None], de[..., None, :]


TOY = RangeSquaredModel()
EXTENDED = COMPONENTS + (TOY,)


def _scene(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    source = np.array([12.0, -7.0, 4.0])
    d = rng.uniform(20.0, 80.0, n)
    az = rng.uniform(-math.pi, math.pi, n)
    el = rng.uniform(-0.6, 0.9, n)
    positions = source - d[:, None] * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    ranging = rng.random(n) < 0.5
    bearing = rng.random(n) < 0.5
    toy = rng.random(n) < 0.6
    los = rng.random(n) < 0.7
    return source, positions, ranging, bearing, toy, los


def test_registry_draws_and_defaults_are_unchanged() -> None:
    assert measurement_draws() == MEASUREMENT_DRAWS
    assert measurement_draws(EXTENDED) == MEASUREMENT_DRAWS + 1


def test_fisher_information_adds_the_toy_term(rng: np.random.Generator) -> None:
    source, positions, ranging, bearing, toy, los = _scene(rng, 9)
    base = fisher_information(source, positions, ranging, bearing, los, CHANNEL)
    # Without the toy's mask the extended registry gives the registry's J, bit for bit.
    np.testing.assert_array_equal(fisher_information(source, positions, ranging, bearing, los, CHANNEL, components=EXTENDED), base)
    J = fisher_information(source, positions, ranging, bearing, los, CHANNEL, {"range_squared": toy}, EXTENDED)
    # Reference: Σ ∇s ∇sᵀ/σ_s² over the drones that measure s, ∇s = 2(p0 − p).
    r = source - positions[toy]
    np.testing.assert_allclose(J - base, 4.0 * r.T @ r / SIGMA_S_M2**2, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("criterion", ["A", "D"])
@pytest.mark.parametrize("own", ["toy", "toy+range", "toy+bearing"])
def test_cost_gradient_matches_finite_differences(criterion: Criterion, own: str, rng: np.random.Generator) -> None:
    source, positions, ranging, bearing, toy, los = _scene(rng, 6)
    i = 0
    ranging[i], bearing[i], toy[i], los[i] = "range" in own, "bearing" in own, True, True
    extra = {"range_squared": toy}

    def C(p: np.ndarray) -> float:
        q = positions.copy()
        q[i] = p
        return float(cost(fisher_information(source, q, ranging, bearing, los, CHANNEL, extra, EXTENDED), criterion)[0])

    J = fisher_information(source, positions, ranging, bearing, los, CHANNEL, extra, EXTENDED)
    own_extra = {"range_squared": toy[i]}
    fast = cost_gradient(J, source, positions[i], ranging[i], bearing[i], los[i], CHANNEL, criterion, own_extra=own_extra, components=EXTENDED)
    batched = cost_gradient(
        J[None],
        source[None],
        positions[i][None],
        ranging[i : i + 1],
        bearing[i : i + 1],
        los[i : i + 1],
        CHANNEL,
        criterion,
        own_extra={"range_squared": toy[i : i + 1]},
        components=EXTENDED,
    )
    h = 1e-4
    fd = np.array([(C(positions[i] + h * e) - C(positions[i] - h * e)) / (2 * h) for e in np.eye(3)])
    scale = np.abs(fd).max()
    np.testing.assert_allclose(fast.gradient, fd, rtol=1e-5, atol=1e-6 * scale)
    np.testing.assert_allclose(batched.gradient[0], fast.gradient, rtol=1e-9, atol=1e-12 * scale)
    # The toy's own term matters: dropping it changes the gradient.
    without = cost_gradient(J, source, positions[i], ranging[i], bearing[i], los[i], CHANNEL, criterion)
    assert np.abs(without.gradient - fast.gradient).max() > 1e-3 * scale


def test_observation_carries_the_toy_values(rng: np.random.Generator) -> None:
    from scipy.special import ndtri

    source, positions, ranging, bearing, toy, los = _scene(rng, 7)
    u = rng.random((7, measurement_draws(EXTENDED)))
    base = observe_from_uniforms(source, positions, ranging, bearing, los, CHANNEL, u[:, :MEASUREMENT_DRAWS])
    obs = observe_from_uniforms(source, positions, ranging, bearing, los, CHANNEL, u, {"range_squared": toy}, EXTENDED)
    for name in ("range_m", "azimuth_rad", "elevation_rad"):
        np.testing.assert_array_equal(obs.values[name], base.values[name])
    d2 = ((source - positions) ** 2).sum(-1)
    expected = np.where(toy, d2 + SIGMA_S_M2 * ndtri(u[:, 5]), np.nan)
    np.testing.assert_allclose(obs.values["range_squared_m2"], expected, rtol=1e-12)
    # observe() draws the extended registry's six variates per drone.
    drawn = observe(
        source, positions, ranging, bearing, np.zeros((0, 3)), np.zeros((0, 3)), CHANNEL, np.random.default_rng(3), {"range_squared": toy}, EXTENDED
    )
    ref = np.random.default_rng(3).random((7, 6))
    np.testing.assert_allclose(drawn.values["range_squared_m2"], np.where(toy, d2 + SIGMA_S_M2 * ndtri(ref[:, 5]), np.nan), rtol=1e-12)


def _records(source: np.ndarray, positions: np.ndarray, rng: np.random.Generator, toy: bool) -> Measurements:
    n = len(positions)
    d = np.linalg.norm(source - positions, axis=-1)
    nan = np.full(n, np.nan)
    ranges = d + 0.05 * d * rng.normal(size=n)
    extra = {"range_squared_m2": d * d + SIGMA_S_M2 * rng.normal(size=n)} if toy else {}
    return Measurements(positions, ranges, nan, nan.copy(), np.ones(n, dtype=bool), extra)


def test_estimator_refinement_uses_the_toy_values(rng: np.random.Generator) -> None:
    source = np.array([12.0, -7.0, 4.0])
    config = EstimatorConfig()
    steps = [source + rng.uniform(-60.0, 60.0, (6, 3)) * np.array([1.0, 1.0, 0.3]) for _ in range(12)]
    seeds = [int(s) for s in rng.integers(0, 2**31, len(steps))]

    def run(components: tuple[SensingComponent, ...], toy: bool) -> EstimatorState:
        state = initial_state((), config)
        for p, seed in zip(steps, seeds, strict=True):
            state = update(state, _records(source, p, np.random.default_rng(seed), toy), CHANNEL, config, components)
        return state

    plain = run(COMPONENTS, False)
    # Toy values the estimator is not given the component for are ignored, bit for bit.
    ignored = run(COMPONENTS, True)
    np.testing.assert_array_equal(ignored.estimate_m, plain.estimate_m)
    np.testing.assert_array_equal(ignored.information, plain.information)
    with_toy = run(EXTENDED, True)
    assert with_toy.initialised and with_toy.observable
    # Every toy value after the initialising call is a used component.
    assert int(with_toy.measurement_count) > int(plain.measurement_count)
    # The toy's information (4 r rᵀ/σ_s² per value, ~10⁴ m⁻² here) dominates the ranges'.
    assert np.trace(with_toy.information) > 3.0 * np.trace(plain.information)
    err_plain = float(np.linalg.norm(plain.estimate_m - source))
    err_toy = float(np.linalg.norm(with_toy.estimate_m - source))
    assert err_toy < err_plain
    assert err_toy < 3.0 * math.sqrt(float(np.trace(np.linalg.inv(with_toy.information))))


# ------------------------------------------------------------------ a mission with the toy
#: The toy's role, and the sensing table that registers it (in this test only).
SQUARED = SensingRole("squared", ("range_squared",), "toy: distance squared s (constant σ_s)")
TOY_SENSING = SensingTable(MappingProxyType({**ROLES, SQUARED.name: SQUARED}), EXTENDED)
PAPER_RANGING = Path(__file__).resolve().parents[2] / "missions" / "paper" / "ranging_los.yaml"
TOY_DRONES = 5
STEPS = 25


def _mission(roles: tuple[str, ...]) -> Mission:
    """The paper's LOS ranging mission (10 drones) with these roles. The mission schema accepts
    the role names of fimnav's table; the toy role is set on the loaded mission."""
    mission = load_mission(PAPER_RANGING)
    return mission.model_copy(update={"drones": mission.drones.model_copy(update={"roles": roles})})


@pytest.fixture(scope="module")
def toy_run() -> tuple[Mission, SimulationResult]:
    mission = _mission(("squared",) * TOY_DRONES + ("ranging",) * (10 - TOY_DRONES))
    return mission, simulate(RunSpec(mission, "A", 1, STEPS), sensing=TOY_SENSING)


def test_the_toy_flies_a_mission(toy_run: tuple[Mission, SimulationResult]) -> None:
    mission, result = toy_run
    config = mission.planner_config(sensing=TOY_SENSING)
    np.testing.assert_array_equal(config.extra_masks["range_squared"], np.arange(10) < TOY_DRONES)
    np.testing.assert_array_equal(config.ranging, np.arange(10) >= TOY_DRONES)
    assert np.isfinite(result.positions_m).all()
    assert np.linalg.norm(result.positions_m[-1] - result.positions_m[0], axis=-1).min() > 1.0
    # The same drones all ranging, with the same draws (the toy table's six per step):
    plain = simulate(RunSpec(_mission(("ranging",) * 10), "A", 1, STEPS), sensing=TOY_SENSING)
    # At step 0 (same positions, every record local) the toy's information (4 r rᵀ/σ_s²) dominates the PEB ...
    assert result.peb_m[0, 0, 0] < 0.2 * plain.peb_m[0, 0, 0]
    # ... the drones fly differently and estimate the source better.
    assert not np.array_equal(result.positions_m[1:], plain.positions_m[1:])
    assert result.estimate_error_m[-1].mean() < plain.estimate_error_m[-1].mean()
    assert result.estimate_error_m[-1].max() < 1.0


def test_the_toy_records_round_trip_the_wire_into_the_estimator(toy_run: tuple[Mission, SimulationResult]) -> None:
    """The records of step k, as the simulator draws them, encoded and decoded with the toy
    table, become the estimator's rows with the toy's values (bit for bit)."""
    mission, result = toy_run
    config = mission.planner_config(sensing=TOY_SENSING)
    k = 7
    positions, source = result.positions_m[k, 0], result.source_m[k]
    uniforms = presampled_uniforms(mission.seed, 1, 10, STEPS, MEASUREMENT_STREAM, TOY_SENSING.measurement_draws())[k, 0]
    los = line_of_sight(positions, source, config.boxes_min_m, config.boxes_max_m)
    obs = observe_from_uniforms(source, positions, config.ranging, config.bearing, los, config.channel, uniforms, config.extra_masks, EXTENDED)
    records = [
        Record(
            j + 1,
            k,
            k * mission.dt_s,
            (float(positions[j, 0]), float(positions[j, 1]), float(positions[j, 2])),
            bool(config.ranging[j]),
            bool(config.bearing[j]),
            bool(obs.los[j]),
            float(obs.range_m[j]),
            float(obs.azimuth_rad[j]),
            float(obs.elevation_rad[j]),
            extra_values={"range_squared_m2": float(obs.values["range_squared_m2"][j])} if config.extra_masks["range_squared"][j] else {},
        )
        for j in range(10)
    ]
    wire = [encode(rec, mission.id, k, sensing=TOY_SENSING) for rec in records]
    # Range-only records have no extension (their bytes are today's); the toy's have one value.
    assert [len(b) for b in wire] == [76 + 9] * TOY_DRONES + [76] * (10 - TOY_DRONES)
    decoded = [decode(b, mission.id, 10, sensing=TOY_SENSING)[1] for b in wire]
    assert [encode(rec, mission.id, k, sensing=TOY_SENSING) for rec in decoded] == wire
    assert [dict(rec.extra_values) for rec in decoded] == [dict(rec.extra_values) for rec in records]
    meas = measurements_from_records([rec for rec in decoded if isinstance(rec, Record)], TOY_SENSING.extra_value_names)
    np.testing.assert_array_equal(meas.extra_values["range_squared_m2"], obs.values["range_squared_m2"])
    np.testing.assert_array_equal(meas.range_m, obs.range_m)
    np.testing.assert_array_equal(meas.positions_m, positions)


def test_the_payload_measures_the_toy_as_the_simulator_does(toy_run: tuple[Mission, SimulationResult]) -> None:
    """A vehicle's payload with the toy component draws the simulator's record of step 0."""
    from vehicle_sim.payload import Payload, PayloadWorld

    mission, result = toy_run
    config = mission.planner_config(sensing=TOY_SENSING)
    source = mission.source
    world = PayloadWorld(tuple(source.position_at(0.0)), (0.0, 0.0, 0.0), (), (), config.channel, mission.seed)
    positions = result.positions_m[0, 0]
    uniforms = presampled_uniforms(mission.seed, 1, 10, 1, MEASUREMENT_STREAM, TOY_SENSING.measurement_draws())[0, 0]
    los = line_of_sight(positions, result.source_m[0], config.boxes_min_m, config.boxes_max_m)
    obs = observe_from_uniforms(
        result.source_m[0], positions, config.ranging, config.bearing, los, config.channel, uniforms, config.extra_masks, EXTENDED
    )
    for drone in (0, TOY_DRONES):
        toy = drone < TOY_DRONES
        payload = Payload(world, drone, ranging=not toy, bearing=False, extra_components=("range_squared",) if toy else (), sensing=TOY_SENSING)
        m = payload.measure(positions[drone], 0, 0.0)
        assert dict(m.extra_values) == ({"range_squared_m2": float(obs.values["range_squared_m2"][drone])} if toy else {})
        assert (m.range_m is None) == toy


def test_the_optimal_placement_counts_the_toy() -> None:
    """``optimal_placement`` with the toy's masks: the PEB it reports is the PEB of J with the
    toy at the placement it returns (recomputed here), and it beats the optimum of the same
    drones all ranging: at 50 m a toy value (4 d²/σ_s² ≈ 6 m⁻²) outweighs a range
    (1/σ_r² ≈ 0.003 m⁻²)."""
    from planner.fim import position_error_bound
    from planner.placement import PlacementBounds, optimal_placement

    source = np.array([0.0, 0.0, 2.0])
    n = 6
    ranging = np.array([True, True, True, False, False, False])
    bearing = np.zeros(n, dtype=bool)
    toy = ~ranging  # three drones measure only the toy: a role of the new component alone
    bounds = PlacementBounds(50.0, 1.0, 5.0, 2.0, 25.0)
    with_toy = optimal_placement(source, ranging, bearing, CHANNEL, bounds, starts=3, extra_masks={"range_squared": toy}, components=EXTENDED)
    los = np.ones(n, dtype=bool)
    J = fisher_information(source, with_toy.positions_m, ranging, bearing, los, CHANNEL, {"range_squared": toy}, EXTENDED)
    assert with_toy.peb_m == pytest.approx(float(position_error_bound(J)[0]), rel=1e-12)
    # The same six drones all ranging instead:
    plain = optimal_placement(source, ranging | toy, bearing, CHANNEL, bounds, starts=3)
    assert with_toy.peb_m < plain.peb_m
    with pytest.raises(ValueError, match="every drone must"):
        optimal_placement(source, ranging, bearing, CHANNEL, bounds, starts=1)
