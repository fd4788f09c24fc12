"""``fimnav missions``: the missions shipped with fimnav.

``fimnav missions list`` (or ``fimnav missions``) prints a table of the bundled missions, by
name, with their drones, roles, steps and criterion; ``fimnav missions show NAME`` prints one
mission's YAML as shipped, to copy and edit (``fimnav missions show paper/joint > my.yaml``).
Every mission argument of ``fimnav`` (``check``, ``launch``, ``montecarlo``, ``plan --mission``,
``vehicle --mission``) takes these names as well as file paths.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

#: Widest description shown in the ``list`` table before it is cut with "...".
DESCRIPTION_WIDTH: int = 60


def register(subparsers: Any) -> None:
    """Add the ``missions`` subcommand (actions ``list`` and ``show``) to the ``fimnav`` parser."""
    p = subparsers.add_parser(
        "missions",
        help="list the missions shipped with fimnav, or print one to copy and edit",
        description="The missions shipped with fimnav. Every command that takes a mission file also takes "
        "one of these names (e.g. fimnav check paper/joint). Without an action: list.",
    )
    actions = p.add_subparsers(dest="action", metavar="ACTION")
    actions.add_parser(
        "list",
        help="table of the bundled missions (name, drones, roles, steps, criterion, description)",
        description="Print a table of the bundled missions: name, drones, roles, steps, criterion, description.",
    )
    show = actions.add_parser(
        "show",
        help="print a bundled mission's YAML (e.g. fimnav missions show paper/joint > my.yaml)",
        description="Print a mission's YAML as shipped, comments included, to copy and edit.",
    )
    show.add_argument("name", metavar="NAME", help="bundled mission name such as paper/joint (or a mission file)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """``fimnav missions [list | show NAME]``. Exit status 0; an unknown name exits 2."""
    if getattr(args, "action", None) == "show":
        return run_show(args.name)
    return run_list()


def run_show(name: str) -> int:
    """Print the YAML text of mission ``name`` unchanged. Exit status 0.

    Raises:
        MissionError: no such bundled mission or file (the nearest names suggested).
    """
    from missions.format.loader import read_mission_text

    text = read_mission_text(name)
    sys.stdout.write(text if text.endswith("\n") or not text else text + "\n")
    return 0


def run_list() -> int:
    """Print the table of bundled missions. Exit status 0."""
    sys.stdout.write(missions_table())
    return 0


def missions_table() -> str:
    """The bundled missions as a text table, one line each, then how to use a name."""
    from missions.format.loader import MissionError, bundled_missions, load_mission

    rows: list[tuple[str, str, str, str, str, str]] = []
    for name, path in bundled_missions().items():
        try:
            mission = load_mission(path)
        except MissionError as exc:
            problem = exc.problems[0] if exc.problems else str(exc)
            rows.append((name, "-", "-", "-", "-", f"invalid: {problem}"))
            continue
        rows.append(
            (
                name,
                str(mission.drones.count),
                roles_summary(mission.drones.roles),
                str(mission.steps),
                mission.criterion,
                _cut(mission.description, DESCRIPTION_WIDTH),
            )
        )
    header = ("name", "drones", "roles", "steps", "criterion", "description")
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    right = {1, 3}  # numbers right-aligned

    def line(cells: tuple[str, ...]) -> str:
        out = [c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths))]
        return "  ".join(out).rstrip()

    body = [line(header), *(line(r) for r in rows)]
    if not rows:
        body.append("(no bundled missions found)")
    body += [
        "",
        "Use a name wherever a mission file is expected: fimnav check NAME, fimnav launch NAME, ...",
        "Copy one to edit it: fimnav missions show NAME > my-mission.yaml",
    ]
    return "\n".join(body) + "\n"


def roles_summary(roles: tuple[str, ...] | list[str]) -> str:
    """Role counts in first-seen order: ``ranging 4, bearing 3, joint 3``."""
    counts: dict[str, int] = {}
    for role in roles:
        counts[role] = counts.get(role, 0) + 1
    return ", ".join(f"{role} {n}" for role, n in counts.items())


def _cut(text: str, width: int) -> str:
    """``text`` on one line, at most ``width`` characters (cut with "...")."""
    flat = " ".join(text.split())
    return flat if len(flat) <= width else flat[: width - 3].rstrip() + "..."
