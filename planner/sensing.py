r"""Sensing models: the roles a drone can have and the physics of what each role measures.

A drone's *role* (paper sec. II-B) says which measurement *components* it takes: ``ranging``
(κ_j = 1) measures the distance d̂, ``bearing`` (β_j = 1) the azimuth φ̂ and elevation θ̂,
``joint`` both. Everything that depends on a role reads it from here:

* :data:`ROLES`, the role table: the mission schema's role names (``missions/format/schema.py``),
  the payload's and the planner's (κ, β) flags (``vehicle_sim/payload.py``,
  :class:`planner.config.PlannerConfig`), the wire format's role bits (``comms/messages.py``).
* :data:`RANGE` and :data:`BEARING`, the measurement components, each with its Fisher
  information term and its gradient (eqs. 10-14) in numpy (the reference the compiled kernels
  of :mod:`planner.kernels` are tested against, and the terms :mod:`planner.radio.unknown_power`
  extends), its measurement simulation (eqs. 3-5, used by :mod:`planner.observation`) and its
  normalised residual (the estimator's likelihood, used by :mod:`planner.estimator.robust`).
  The planning step itself uses the compiled terms.

Notation (mission ENU frame, metres, radians): drone at p, source p0, r = p0 − p, d = ‖r‖,
ρ = √(r_x² + r_y²), b = (−r_y, r_x, 0) = ∇φ·ρ², v = (−r_x r_z, −r_y r_z, ρ²) = ∇θ·d²ρ:

.. math::
    J = \sum_j \kappa_j A_{r,j}\,\mathbf a_j\mathbf a_j^T
        + \beta_j p_j \frac{1}{\sigma_{b,0}^2}\big(\nabla\phi_j\nabla\phi_j^T
        + \nabla\theta_j\nabla\theta_j^T\big),\qquad
    A_{r} = \frac{1}{\sigma_{r}^2} + \frac{\gamma^2}{2 d^2},\quad
    \sigma_{r}^2 = \sigma_{r,0}^2 d^{\gamma}

See ``docs/sensing-models.md`` for adding a sensing model.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import ClassVar, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.geometry import RHO_FLOOR_M
from planner.params import Channel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
MaskT = TypeVar("MaskT")

#: Role bits of the wire format (``comms/messages.py``): one bit per measurement component.
RANGING_BIT: int = 1
BEARING_BIT: int = 2


@dataclass(frozen=True)
class SensingRole:
    """One sensing role of the role table.

    Attributes:
        name: the role's name in mission files and user-facing text.
        components: the names of the measurement components the role takes (see
            :data:`COMPONENTS`), e.g. ``("range",)``.
        description: one line for the mission schema and the docs.
    """

    name: str
    components: tuple[str, ...]
    description: str

    @property
    def ranging(self) -> bool:
        """κ_j: the role measures range (:data:`RANGE`)."""
        return RANGE.name in self.components

    @property
    def bearing(self) -> bool:
        """β_j: the role measures azimuth and elevation (:data:`BEARING`)."""
        return BEARING.name in self.components

    @property
    def wire_bits(self) -> int:
        """The role byte of a record on the wire: the OR of its components' ``wire_bit``."""
        bits = 0
        for component in COMPONENTS:
            if component.name in self.components:
                bits |= component.wire_bit
        return bits


#: The role table, in the order the docs and the schema list it (read-only).
ROLES: Mapping[str, SensingRole] = MappingProxyType(
    {
        role.name: role
        for role in (
            SensingRole("ranging", ("range",), "RSS ranging d̂ (paper N_R, κ_j = 1)"),
            SensingRole("bearing", ("bearing",), "azimuth and elevation φ̂, θ̂ (paper N_B, β_j = 1)"),
            SensingRole("joint", ("range", "bearing"), "ranging and bearing (κ_j = β_j = 1)"),
        )
    }
)
#: The role names, in table order.
ROLE_NAMES: tuple[str, ...] = tuple(ROLES)


def sensing_role(name: str) -> SensingRole:
    """The role called ``name``.

    Raises:
        ValueError: an unknown name; the message lists the roles and suggests the nearest.
    """
    return SENSING.role(name)


def role_from_flags(ranging: bool, bearing: bool) -> SensingRole:
    """The role with the flags (κ, β).

    Raises:
        ValueError: no role has them (a drone that measures nothing).
    """
    for role in ROLES.values():
        if role.ranging == bool(ranging) and role.bearing == bool(bearing):
            return role
    raise ValueError(f"no sensing role measures ranging={bool(ranging)}, bearing={bool(bearing)}")


def role_masks(names: Iterable[str]) -> tuple[BoolArray, BoolArray]:
    """(κ, β) masks, each (N,) bool, of N drones' role names."""
    roles = [sensing_role(n) for n in names]
    return np.array([r.ranging for r in roles], dtype=bool), np.array([r.bearing for r in roles], dtype=bool)


def wrap_angle(angle: FloatArray) -> FloatArray:
    """Wrap an angle difference to [-π, π] (radians)."""
    return angle - (2.0 * np.pi) * np.rint(angle * (0.5 / np.pi))


# --------------------------------------------------------------------------- components
@dataclass(frozen=True)
class LinkGeometry:
    """Geometry of drone-to-source links, shared by every component's terms.

    Attributes:
        r: p0 − p, shape (..., 3), m, ENU.
        rho2: ρ² = r_x² + r_y², floored at ``RHO_FLOOR_M``², shape (...), m².
        d2: d² = ρ² + r_z², m². d: d, m.
    """

    r: FloatArray
    rho2: FloatArray
    d2: FloatArray
    d: FloatArray


def link_geometry(r: FloatArray) -> LinkGeometry:
    """:class:`LinkGeometry` of relative vectors r = p0 − p, shape (..., 3), m."""
    rx, ry, rz = r[..., 0], r[..., 1], r[..., 2]
    rho2 = np.maximum(rx * rx + ry * ry, RHO_FLOOR_M**2)
    d2 = rho2 + rz * rz
    return LinkGeometry(r, rho2, d2, np.sqrt(d2))


class SensingComponent:
    r"""What a measurement component supplies to the math core (base class of the components).

    A component measures ``len(value_names)`` scalars per drone and step and adds
    ``fim_row_count`` rank-one terms w u uᵀ to the Fisher information J of the source position
    (u: a row vector, (..., 3), w: its weight, both per drone). Everything that loops over
    components (:mod:`planner.fim`, :mod:`planner.observation`, :mod:`planner.estimator`)
    calls the methods below, in the order of :data:`COMPONENTS`.

    Class attributes:
        name: the component's name (the key of its mask, e.g. ``"range"``).
        wire_bit: its bit in a record's role byte (``comms/messages.py``).
        value_names: the names of its measured values, with units (e.g. ``("range_m",)``):
            the keys of :attr:`planner.observation.Observation.values` and of
            :attr:`planner.estimator.Measurements.values` (for components outside the
            estimator's built-in kernel).
        uniform_columns: the columns of a drone's uniform variates per step it draws from.
        fim_row_count: the number of rows u it adds to J.
    """

    name: ClassVar[str] = ""
    wire_bit: ClassVar[int] = 0
    value_names: ClassVar[tuple[str, ...]] = ()
    uniform_columns: ClassVar[tuple[int, ...]] = ()
    fim_row_count: ClassVar[int] = 0

    def simulate_values(
        self, d: FloatArray, phi: FloatArray, theta: FloatArray, los: BoolArray, channel: Channel, uniforms: FloatArray
    ) -> tuple[FloatArray, ...]:
        """The measured values (one per ``value_names``, each (..., N)) of true distances d (m),
        azimuths φ and elevations θ (rad), (..., N), from the uniforms (..., N, U) (eq. 3)."""
        raise NotImplementedError(f"{type(self).__name__}.simulate_values")

    def fim_vectors(self, geom: LinkGeometry) -> FloatArray:
        """The rows u of its terms w u uᵀ of J, shape (..., ``fim_row_count``, 3)."""
        raise NotImplementedError(f"{type(self).__name__}.fim_vectors")

    def fim_row_weights(self, geom: LinkGeometry, mask: ArrayLike, los_w: FloatArray, channel: Channel) -> FloatArray:
        """The weights w of its rows, shape (..., ``fim_row_count``), zero where ``mask``
        (bool, (..., N)) is False; ``los_w``: the link's LOS flag or weight q in [0, 1]."""
        raise NotImplementedError(f"{type(self).__name__}.fim_row_weights")

    def cost_gradient_terms(
        self, geom: LinkGeometry, q: FloatArray, MV: FloatArray, mask: ArrayLike, los_w: FloatArray, channel: Channel, los_trace: bool
    ) -> tuple[FloatArray, FloatArray | None]:
        """∂ tr(M J_c)/∂r (..., 3) of its own term J_c of one drone's J (``mask``: the drone has
        the component), and, if ``los_trace``, tr(M ∂J_c/∂q) (...) of the LOS weight q.
        ``q`` (..., k) = uᵀMu and ``MV`` (..., k, 3) = M u of its rows u (M symmetric)."""
        raise NotImplementedError(f"{type(self).__name__}.cost_gradient_terms")

    def estimator_terms(self, values: tuple[FloatArray, ...], geom: LinkGeometry, channel: Channel) -> tuple[FloatArray, FloatArray]:
        """The estimator's normalised residuals e = (z − h(p0))/σ of the measured ``values``
        (each (..., K)) at links ``geom`` of a source candidate p0, shape (..., K, n) with n =
        ``len(value_names)``, and their gradients ∂e/∂p0, shape (..., K, n, 3), m⁻¹ (for σ that
        does not depend on p0). The estimator's robust refinement sums a ρ(e) over them
        (:mod:`planner.estimator.robust`)."""
        raise NotImplementedError(f"{type(self).__name__}.estimator_terms")


@dataclass(frozen=True)
class RangeModel(SensingComponent):
    """Ranging component d̂ = d + n_r, n_r ~ N(0, σ_r0² d^γ) (eqs. 3, 5), σ_r0 = (ln10/10)(σ_sh/γ)
    of the link's LOS or NLOS ratio. It uses uniform variate 0 of a drone's five per step."""

    name: ClassVar[str] = "range"
    wire_bit: ClassVar[int] = RANGING_BIT
    value_names: ClassVar[tuple[str, ...]] = ("range_m",)
    uniform_columns: ClassVar[tuple[int, ...]] = (0,)
    fim_row_count: ClassVar[int] = 1

    def simulate_values(
        self, d: FloatArray, phi: FloatArray, theta: FloatArray, los: BoolArray, channel: Channel, uniforms: FloatArray
    ) -> tuple[FloatArray, ...]:
        """(d̂,) of :meth:`simulate`."""
        return (self.simulate(d, los, channel, uniforms),)

    def fim_vectors(self, geom: LinkGeometry) -> FloatArray:
        """u = r (ranging direction times d)."""
        return geom.r[..., None, :]

    @staticmethod
    def _inv_s0sq(los_w: FloatArray, channel: Channel) -> FloatArray:
        """q/σ_r0,LOS² + (1 − q)/σ_r0,NLOS² of the LOS weight q, m⁻²."""
        return los_w / channel.sigma_r0_los**2 + (1.0 - los_w) / channel.sigma_r0_nlos**2

    def fim_row_weights(self, geom: LinkGeometry, mask: ArrayLike, los_w: FloatArray, channel: Channel) -> FloatArray:
        """κ A_r/d² (A_r a aᵀ = (A_r/d²) r rᵀ), m⁻⁴."""
        inv_s0sq = self._inv_s0sq(los_w, channel)
        w = np.asarray(mask, dtype=bool) * self.fim_weight(geom.d, geom.d2, inv_s0sq, channel.gamma) / geom.d2
        return np.broadcast_to(w, np.broadcast_shapes(np.shape(w), geom.d.shape))[..., None]

    def cost_gradient_terms(
        self, geom: LinkGeometry, q: FloatArray, MV: FloatArray, mask: ArrayLike, los_w: FloatArray, channel: Channel, los_trace: bool
    ) -> tuple[FloatArray, FloatArray | None]:
        """κ :meth:`cost_gradient` and κ :meth:`los_trace`."""
        inv_s0sq = self._inv_s0sq(los_w, channel)
        g_r = self.cost_gradient(geom.r, geom.d, geom.d2, q[..., 0], MV[..., 0, :], inv_s0sq, channel.gamma)
        use_r = np.asarray(mask, dtype=bool)[..., None]
        tr = use_r[..., 0] * self.los_trace(geom.d, geom.d2, q[..., 0], channel) if los_trace else None
        return use_r * g_r, tr

    def std_m(self, d: ArrayLike, los: ArrayLike, channel: Channel) -> FloatArray:
        """σ_r = σ_r0 d^(γ/2) of eq. 5 (m), with σ_r0 for LOS or NLOS per link."""
        s0 = channel.sigma_r0(los)
        return s0 * np.asarray(d, dtype=float) ** (0.5 * channel.gamma)

    def simulate(self, d: FloatArray, los: BoolArray, channel: Channel, uniforms: FloatArray) -> FloatArray:
        """d̂ (m) of true distances d (..., N), m, from the uniforms (..., N, 5) (eq. 3)."""
        from scipy.special import ndtri  # imported here: the planner node never simulates

        z = ndtri(np.maximum(uniforms[..., 0], 1e-300))
        return d + self.std_m(d, los, channel) * z

    def fim_weight(self, d: FloatArray, d2: FloatArray, inv_s0sq: FloatArray, gamma: float) -> FloatArray:
        """A_r = d^−γ/σ_r0² + γ²/(2d²) (eq. 12 with the variance term), m⁻²: J_r = A_r a aᵀ
        = (A_r/d²) r rᵀ. ``inv_s0sq``: 1/σ_r0² (LOS/NLOS mix by the LOS weight)."""
        return d ** (-gamma) * inv_s0sq + gamma * gamma / (2.0 * d2)

    def cost_gradient(
        self, r: FloatArray, d: FloatArray, d2: FloatArray, q_r: FloatArray, Mr: FloatArray, inv_s0sq: FloatArray, gamma: float
    ) -> FloatArray:
        """∂ tr(M J_r)/∂r (..., 3) for J_r = h(d) r rᵀ, h = d^−γ/(σ_r0² d²) + γ²/(2d⁴):
        (h'(d)/d)(rᵀMr) r + 2h M r (eq. 14's own term). ``q_r`` = rᵀMr, ``Mr`` = M r."""
        h = d ** (-gamma) * inv_s0sq / d2 + gamma * gamma / (2.0 * d2 * d2)
        dh = (-gamma - 2.0) * d ** (-gamma - 3.0) * inv_s0sq - 2.0 * gamma * gamma / (d2 * d2 * d)
        return (dh / d * q_r)[..., None] * r + 2.0 * h[..., None] * Mr

    def los_trace(self, d: FloatArray, d2: FloatArray, q_r: FloatArray, channel: Channel) -> FloatArray:
        """tr(M (J_r,LOS − J_r,NLOS)) = d^−γ (1/σ_r0,LOS² − 1/σ_r0,NLOS²)/d² · rᵀMr."""
        return d ** (-channel.gamma) * (1.0 / channel.sigma_r0_los**2 - 1.0 / channel.sigma_r0_nlos**2) / d2 * q_r

    def normalised_residual(self, z: FloatArray, d: FloatArray, inv_sr: FloatArray) -> FloatArray:
        """e = (d̂ − d)/σ_r, the estimator's normalised range residual (σ_r: 1/``inv_sr``, m)."""
        e = z - d
        e *= inv_sr
        return e


@dataclass(frozen=True)
class BearingModel(SensingComponent):
    """Bearing component (φ̂, θ̂) = (φ, θ) + n_b, n_b ~ N(0, σ_b,0² I₂) in LOS, the uniform
    outlier ω (azimuth on [−π, π), elevation on [−π/2, π/2]) in NLOS (eq. 3). It uses uniform
    variates 1, 2 (noise) and 3, 4 (outlier) of a drone's five per step."""

    name: ClassVar[str] = "bearing"
    wire_bit: ClassVar[int] = BEARING_BIT
    value_names: ClassVar[tuple[str, ...]] = ("azimuth_rad", "elevation_rad")
    uniform_columns: ClassVar[tuple[int, ...]] = (1, 2, 3, 4)
    fim_row_count: ClassVar[int] = 2

    def simulate_values(
        self, d: FloatArray, phi: FloatArray, theta: FloatArray, los: BoolArray, channel: Channel, uniforms: FloatArray
    ) -> tuple[FloatArray, ...]:
        """(φ̂, θ̂) of :meth:`simulate`."""
        return self.simulate(phi, theta, los, channel, uniforms)

    def fim_vectors(self, geom: LinkGeometry) -> FloatArray:
        """u = b = (−r_y, r_x, 0) (∇φ·ρ²) and v = (−r_x r_z, −r_y r_z, ρ²) (∇θ·d²ρ)."""
        r = geom.r
        rx, ry, rz = r[..., 0], r[..., 1], r[..., 2]
        u = np.empty(r.shape[:-1] + (2, 3))
        u[..., 0, 0] = -ry
        u[..., 0, 1] = rx
        u[..., 0, 2] = 0.0
        u[..., 1, 0] = -rx * rz
        u[..., 1, 1] = -ry * rz
        u[..., 1, 2] = geom.rho2
        return u

    def fim_row_weights(self, geom: LinkGeometry, mask: ArrayLike, los_w: FloatArray, channel: Channel) -> FloatArray:
        """:meth:`fim_weights` with ``bearing_los`` = β q."""
        w_b, w_v = self.fim_weights(geom.rho2, geom.d2, np.asarray(mask, dtype=bool) * los_w, channel)
        shape = np.broadcast_shapes(np.shape(w_b), np.shape(w_v), geom.d.shape)
        return np.stack((np.broadcast_to(w_b, shape), np.broadcast_to(w_v, shape)), axis=-1)

    def cost_gradient_terms(
        self, geom: LinkGeometry, q: FloatArray, MV: FloatArray, mask: ArrayLike, los_w: FloatArray, channel: Channel, los_trace: bool
    ) -> tuple[FloatArray, FloatArray | None]:
        """β q ∂ tr(M (J_az + J_el))/∂r of :meth:`cost_gradient`, and β tr(M (J_az + J_el))."""
        g_b, tr_b = self.cost_gradient(geom.r, geom.rho2, geom.d2, q[..., 0], q[..., 1], MV[..., 0, :], MV[..., 1, :], channel)
        has = np.asarray(mask, dtype=bool)
        return (has * los_w)[..., None] * g_b, has * tr_b if los_trace else None

    def simulate(self, phi: FloatArray, theta: FloatArray, los: BoolArray, channel: Channel, uniforms: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(φ̂, θ̂) (rad) of true angles (..., N) from the uniforms (..., N, 5) (eq. 3)."""
        from scipy.special import ndtri  # imported here: the planner node never simulates

        z = ndtri(np.maximum(uniforms[..., 1:3], 1e-300))
        sb = channel.sigma_bearing_rad
        unit = np.exp(1j * (phi + sb * z[..., 0]))
        az_los = np.arctan2(unit.imag, unit.real)  # the angle of the unit vector: wrapped to (-π, π]
        el_los = np.minimum(np.maximum(theta + sb * z[..., 1], -0.5 * np.pi), 0.5 * np.pi)
        az_out = -np.pi + 2.0 * np.pi * uniforms[..., 3]
        el_out = -0.5 * np.pi + np.pi * uniforms[..., 4]
        return np.where(los, az_los, az_out), np.where(los, el_los, el_out)

    def fim_weights(self, rho2: FloatArray, d2: FloatArray, bearing_los: FloatArray, channel: Channel) -> tuple[FloatArray, FloatArray]:
        """Weights of b bᵀ and v vᵀ in J (eqs. 10-11, Cartesian form), m⁻⁴ and m⁻⁶:
        ∇φ∇φᵀ/σ_b² = b bᵀ/(σ_b² ρ⁴), ∇θ∇θᵀ/σ_b² = v vᵀ/(σ_b² d⁴ ρ²), times ``bearing_los``
        = β p (an NLOS bearing carries no information; a LOS weight q gives q)."""
        w_b = bearing_los / (channel.sigma_bearing_rad**2 * rho2)
        return w_b / rho2, w_b / (d2 * d2)

    def cost_gradient(
        self, r: FloatArray, rho2: FloatArray, d2: FloatArray, q_b: FloatArray, q_v: FloatArray, Mb: FloatArray, Mv: FloatArray, channel: Channel
    ) -> tuple[FloatArray, FloatArray]:
        """∂ tr(M (J_az + J_el))/∂r (..., 3) of the azimuth term w b bᵀ, w = 1/(σ_b² ρ⁴)
        (∂b/∂r = R, Rᵀx = (x_y, −x_x, 0)), and of the elevation term c² v vᵀ/σ_b², c = 1/(d² ρ)
        (∂v/∂r = [[−r_z, 0, −r_x], [0, −r_z, −r_y], [2r_x, 2r_y, 0]]); and the trace
        tr(M (J_az + J_el)) (the LOS weight's term). ``q_b``, ``q_v`` = bᵀMb, vᵀMv; ``Mb``,
        ``Mv`` = M b, M v."""
        rx, ry, rz = r[..., 0], r[..., 1], r[..., 2]
        sb2 = channel.sigma_bearing_rad**2
        w_az = 1.0 / (sb2 * rho2 * rho2)
        horiz = r.copy()
        horiz[..., 2] = 0.0
        RtMb = np.empty_like(r)
        RtMb[..., 0] = Mb[..., 1]
        RtMb[..., 1] = -Mb[..., 0]
        RtMb[..., 2] = 0.0
        g_az = 2.0 * w_az[..., None] * RtMb - (4.0 * w_az * q_b / rho2)[..., None] * horiz
        c2 = 1.0 / (d2 * d2 * rho2)
        VtMv = np.empty_like(r)
        VtMv[..., 0] = -rz * Mv[..., 0] + 2.0 * rx * Mv[..., 2]
        VtMv[..., 1] = -rz * Mv[..., 1] + 2.0 * ry * Mv[..., 2]
        VtMv[..., 2] = -rx * Mv[..., 0] - ry * Mv[..., 1]
        grad_c2 = -2.0 * c2[..., None] * (2.0 * r / d2[..., None] + horiz / rho2[..., None])
        g_el = (2.0 * c2[..., None] * VtMv + q_v[..., None] * grad_c2) / sb2
        return g_az + g_el, w_az * q_b + c2 * q_v / sb2

    def normalised_residuals(
        self, za: FloatArray, ze: FloatArray, rx: FloatArray, ry: FloatArray, rz: FloatArray, rho: FloatArray, inv_sb: float
    ) -> tuple[FloatArray, FloatArray]:
        """(e_φ, e_θ) = (wrap(φ̂ − φ), θ̂ − θ)/σ_b, the estimator's normalised bearing residuals
        at r = p0 − p (m) with horizontal distance ρ (m); 1/σ_b = ``inv_sb`` (rad⁻¹)."""
        ea = wrap_angle(za - np.arctan2(ry, rx))
        ea *= inv_sb
        ee = ze - np.arctan2(rz, rho)
        ee *= inv_sb
        return ea, ee


#: The ranging component (κ_j).
RANGE: RangeModel = RangeModel()
#: The bearing component (β_j).
BEARING: BearingModel = BearingModel()
#: The component registry, in the order the Fisher information stacks their rows and a record
#: lists their values. A new component is one more entry here (and a role that takes it).
COMPONENTS: tuple[SensingComponent, ...] = (RANGE, BEARING)


def component_masks(
    ranging: ArrayLike, bearing: ArrayLike, extra: Mapping[str, ArrayLike] | None = None, components: Sequence[SensingComponent] = COMPONENTS
) -> tuple[ArrayLike, ...]:
    """Per-drone masks of ``components``, in their order: κ for :data:`RANGE`, β for
    :data:`BEARING`, ``extra[name]`` for any other component (False where not given).

    Raises:
        ValueError: ``extra`` names a component not in ``components``.
    """
    names = [c.name for c in components]
    unknown = sorted(set(extra or {}) - set(names))
    if unknown:
        raise ValueError(f"component masks: expected names among {names}, found {unknown}")
    by_name: dict[str, ArrayLike] = {RANGE.name: ranging, BEARING.name: bearing, **(extra or {})}
    return tuple(by_name.get(name, False) for name in names)


@dataclass(frozen=True, eq=False)
class SensingTable:
    """A role table with its component registry: what a mission's roles mean for the planner,
    the simulator and the wire format. :data:`SENSING` is fimnav's (:data:`ROLES`,
    :data:`COMPONENTS`); a test may build a larger one (a toy component and a role taking it)
    and pass it where ``sensing=`` is accepted.

    Attributes:
        roles: role name -> :class:`SensingRole` (read-only mapping).
        components: the measurement components, in registry order; range and bearing first.

    Raises:
        ValueError: two components share a name or a wire bit, a wire bit is not a single bit
            of the role byte, or a role names a component not in ``components``.
    """

    roles: Mapping[str, SensingRole]
    components: tuple[SensingComponent, ...]

    def __post_init__(self) -> None:
        names = [c.name for c in self.components]
        bits = [c.wire_bit for c in self.components]
        if names[:2] != [RANGE.name, BEARING.name] or len(set(names)) != len(names):
            raise ValueError(f"sensing table: expected distinct component names starting with range, bearing; found {names}")
        if len(set(bits)) != len(bits) or any(b <= 0 or b > 0x80 or b & (b - 1) for b in bits):
            raise ValueError(f"sensing table: expected distinct single-bit wire bits of a byte, found {bits}")
        for role in self.roles.values():
            unknown = sorted(set(role.components) - set(names))
            if unknown:
                raise ValueError(f"sensing table: role {role.name!r} names components {unknown}, expected among {names}")

    @property
    def extra_components(self) -> tuple[SensingComponent, ...]:
        """The components other than range and bearing, in registry order."""
        return self.components[2:]

    @property
    def extra_value_names(self) -> tuple[str, ...]:
        """The value names of :attr:`extra_components`, in registry order."""
        return tuple(name for c in self.extra_components for name in c.value_names)

    def role(self, name: str) -> SensingRole:
        """The role called ``name``.

        Raises:
            ValueError: an unknown name; the message lists the roles and suggests the nearest.
        """
        role = self.roles.get(name)
        if role is None:
            names = tuple(self.roles)
            near = difflib.get_close_matches(str(name), names, n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            raise ValueError(f"role: expected one of {sorted(names)}, found {name!r}{hint}")
        return role

    def masks(self, role_names: Iterable[str]) -> Mapping[str, BoolArray]:
        """Per-drone masks of every component, by component name, each (N,) bool, of N drones'
        role names (read-only mapping, registry order)."""
        roles = [self.role(n) for n in role_names]
        return MappingProxyType({c.name: np.array([c.name in r.components for r in roles], dtype=bool) for c in self.components})

    def wire_bits(self, components: Iterable[str]) -> int:
        """The role byte of a record whose sender takes ``components`` (names): the OR of their
        ``wire_bit``."""
        taken = set(components)
        return sum(c.wire_bit for c in self.components if c.name in taken)

    def role_of_bits(self, bits: int) -> SensingRole | None:
        """The role whose role byte is ``bits``; None if no role has it."""
        for role in self.roles.values():
            if self.wire_bits(role.components) == bits:
                return role
        return None

    def measurement_draws(self) -> int:
        """Uniform variates per drone and step its components draw from (:func:`measurement_draws`)."""
        return measurement_draws(self.components)


def extra_masks(masks: Mapping[str, MaskT]) -> Mapping[str, MaskT]:
    """The masks of ``masks`` other than range's and bearing's (the ``extra_masks`` /
    ``own_extra`` arguments of :mod:`planner.fim` and :mod:`planner.observation`)."""
    return MappingProxyType({name: m for name, m in masks.items() if name not in (RANGE.name, BEARING.name)})


def measurement_draws(components: Sequence[SensingComponent] = COMPONENTS) -> int:
    """Uniform variates per drone and step that ``components`` draw from (5 for the registry)."""
    columns = [col for c in components for col in c.uniform_columns]
    if len(set(columns)) != len(columns):
        raise ValueError(f"components: expected disjoint uniform columns, found {columns}")
    return max(columns, default=-1) + 1


#: fimnav's sensing table: :data:`ROLES` with :data:`COMPONENTS`.
SENSING: SensingTable = SensingTable(ROLES, COMPONENTS)


__all__ = [
    "BEARING",
    "BEARING_BIT",
    "COMPONENTS",
    "RANGE",
    "RANGING_BIT",
    "ROLES",
    "ROLE_NAMES",
    "SENSING",
    "BearingModel",
    "LinkGeometry",
    "RangeModel",
    "SensingComponent",
    "SensingRole",
    "SensingTable",
    "component_masks",
    "extra_masks",
    "link_geometry",
    "measurement_draws",
    "role_from_flags",
    "role_masks",
    "sensing_role",
    "wrap_angle",
]
