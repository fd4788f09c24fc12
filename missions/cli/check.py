"""``fimnav check MISSION.yaml`` and ``fimnav schema``: validate a mission, print the format.

``check`` prints a one-screen summary and exits 0, or prints one error message (file, line,
key path, expected, found) and exits 2. The mission is a file path or, when no such file
exists, the name of a bundled mission (``paper/joint``; see ``fimnav missions list``).
``schema`` prints the JSON Schema (draft 2020-12) of the mission format to stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import numpy as np


def register(subparsers: Any) -> None:
    """Add the ``check`` and ``schema`` subcommands to the ``fimnav`` parser."""
    check = subparsers.add_parser(
        "check",
        help="validate a mission file and print a summary",
        description="Validate a mission file; print a one-screen summary (exit 0) or the error (exit 2).",
    )
    check.add_argument(
        "mission",
        metavar="MISSION",
        help="mission file, or the name of a mission shipped with fimnav such as paper/joint (fimnav missions list)",
    )
    add_override_arguments(check)
    check.add_argument("--yaml", action="store_true", help="print the mission as run (defaults filled) instead")
    check.set_defaults(func=run_check)

    schema = subparsers.add_parser(
        "schema",
        help="print the JSON Schema of the mission format",
        description="Print the JSON Schema (draft 2020-12) of the mission format to stdout.",
    )
    schema.add_argument("--indent", type=int, default=2, help="JSON indentation (default 2)")
    schema.set_defaults(func=run_schema)


def add_override_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--criterion A|D`` and repeatable ``--set KEY=VALUE`` (for any mission command)."""
    parser.add_argument("--criterion", choices=("A", "D"), help="override the design criterion")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a mission value, e.g. --set constraints.activation=paper (repeatable)",
    )


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The overrides mapping for :func:`missions.format.loader.load_mission` from ``--set``/``--criterion``."""
    from missions.format.loader import parse_overrides

    overrides = parse_overrides(getattr(args, "overrides", None) or [])
    if getattr(args, "criterion", None):
        overrides["criterion"] = args.criterion
    return overrides


def run_check(args: argparse.Namespace) -> int:
    """Validate ``args.mission``; print the summary (or the YAML as run). Exit status 0."""
    from missions.format.loader import load_mission, mission_to_yaml

    mission = load_mission(args.mission, overrides_from_args(args))
    text = mission_to_yaml(mission) if args.yaml else summary(mission, str(args.mission))
    sys.stdout.write(text if text.endswith("\n") else text + "\n")
    return 0


def run_schema(args: argparse.Namespace) -> int:
    """Print the mission JSON Schema. Exit status 0."""
    from missions.format.schema import mission_json_schema

    sys.stdout.write(json.dumps(mission_json_schema(), indent=args.indent, ensure_ascii=False) + "\n")
    return 0


def _v(values: Any) -> str:
    return "[" + ", ".join(f"{float(x):g}" for x in values) + "]"


def summary(mission: Any, file: str) -> str:
    """A one-screen text summary of a valid :class:`missions.format.schema.Mission`."""
    m = mission
    d = m.drones
    lines = [f"{file}: OK", f"mission    {m.id}" + (f" - {m.description}" if m.description else "")]
    lines.append(
        f"run        seed {m.seed}, {m.trials} trials x {m.steps} steps of {m.dt_s:g} s "
        f"({m.duration_s:g} s), criterion {m.criterion}-optimal, activation {m.constraints.activation}"
    )
    lines.append(f"origin     {m.origin.lat_deg:.6f} deg, {m.origin.lon_deg:.6f} deg, {m.origin.alt_m:g} m AMSL")
    groups: dict[str, list[int]] = {}
    for i, role in enumerate(d.roles, start=1):
        groups.setdefault(role, []).append(i)
    roles = "; ".join(f"{role} {_ids(ids)}" for role, ids in groups.items())
    lines.append(f"drones     {d.count}: {roles}")
    starts = d.start_positions_m()
    if d.start.ellipse is not None:
        e = d.start.ellipse
        how = f"ellipse in XZ, centre {_v(e.center_m)} m, r_x {e.radius_x_m:g} m, r_z {e.radius_z_m:g} m, phase {e.phase_deg:g} deg"
    else:
        how = "explicit positions"
    lines.append(f"start      {how}")
    lines.append(
        f"           x {starts[:, 0].min():.1f}..{starts[:, 0].max():.1f}, y {starts[:, 1].min():.1f}.."
        f"{starts[:, 1].max():.1f}, z {starts[:, 2].min():.1f}..{starts[:, 2].max():.1f} m"
    )
    src = m.source
    motion = "static" if src.is_static else f"moving {_v(src.velocity_mps)} m/s, at end {_v(src.position_at(m.duration_s))} m"
    dist = np.linalg.norm(starts - src.position_at(0.0), axis=-1)
    lines.append(f"source     {_v(src.position_m)} m, {motion}; {dist.min():.1f}..{dist.max():.1f} m from the starts")
    if src.power != "known" or src.power_offset_db != 0.0:
        power = "unknown (estimated with the position)" if src.power == "unknown" else "known (nominal assumed)"
        lines.append(f"           power {power}; true offset {src.power_offset_db:+g} dB (simulation)")
    if m.obstacles:
        lines.append(f"obstacles  {len(m.obstacles)}:")
        lines.extend(
            f"           {b.name}: x {b.min_m[0]:g}..{b.max_m[0]:g}, y {b.min_m[1]:g}..{b.max_m[1]:g}, z {b.min_m[2]:g}..{b.max_m[2]:g} m"
            for b in m.obstacles
        )
    else:
        lines.append("obstacles  none (line of sight everywhere)")
    ch = m.channel
    lines.append(
        f"channel    gamma {ch.path_loss_exponent:g}, sigma_sh/gamma {ch.sigma_ratio_los:g} LOS / "
        f"{ch.sigma_ratio_nlos:g} NLOS, sigma_b {ch.sigma_bearing_deg:g} deg"
    )
    c = m.constraints
    lines.append(
        f"limits     d_U* {c.d_uav_m:g} m, d_S* {c.d_source_m:g} m, d_O* {c.d_obstacle_m:g} m, "
        f"v {c.speed_min_mps:g}..{c.speed_max_mps:g} m/s, phi/theta max {c.heading_change_max_deg:g}/"
        f"{c.tilt_change_max_deg:g} deg/step, z {c.z_min_m:g}..{c.z_max_m:g} m"
    )
    f = m.fence
    lines.append(f"fence      x {f.x_min_m:g}..{f.x_max_m:g} m, y {f.y_min_m:g}..{f.y_max_m:g} m")
    cm = m.comms
    lines.append(f"comms      d_hop {cm.d_hop_m:g} m, h_max {cm.h_max}, latency {cm.latency}")
    z = m.zenoh
    secure = ", ".join(x for x, on in (("TLS", z.tls is not None), ("auth", z.auth is not None)) if on) or "no TLS, no auth"
    lines.append(f"zenoh      {z.mode}, listen {list(z.listen)}, connect {list(z.connect)}, {secure}")
    external = sum(1 for i in range(d.count) if m.vehicles.for_drone(i).connection is not None)
    lines.append(
        f"vehicles   {m.vehicles.flavour}, profile {m.vehicles.profile}, {d.count - external} simulated, "
        f"{external} external; end action {m.end_action}"
    )
    return "\n".join(lines) + "\n"


def _ids(ids: list[int]) -> str:
    if ids == list(range(ids[0], ids[-1] + 1)) and len(ids) > 2:
        return f"{ids[0]}-{ids[-1]}"
    return "{" + ", ".join(str(i) for i in ids) + "}"
