"""``fimnav view RESULTS``: replay a run's recorded live view in a browser.

``fimnav launch --view`` records ``RESULTS/view.rrd``; ``fimnav montecarlo --view`` records
``RESULTS/view/<run>.rrd``. This command serves them with rerun's web viewer on 127.0.0.1 and
prints the address to open; Ctrl-C stops it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from comms.errors import UsageError


def register(subparsers: Any) -> None:
    """Add the ``view`` subcommand."""
    p = subparsers.add_parser(
        "view",
        help="replay the live view recorded by launch --view or montecarlo --view, in a browser",
        description="Serve a run's recorded view (RESULTS/view.rrd, RESULTS/view/*.rrd, or an .rrd file) with rerun's web "
        "viewer on 127.0.0.1 and print the address to open. Needs pip install 'fimnav[view]'.",
    )
    p.add_argument("results", type=Path, metavar="RESULTS", help="a results directory, or a recording (.rrd)")
    p.add_argument("--port", type=int, help="the web viewer's port (default: a free one)")
    p.set_defaults(func=run)


def recordings(path: Path) -> list[Path]:
    """The recordings a results directory (or an .rrd file) holds; a UsageError naming what
    is missing otherwise."""
    if path.is_file():
        if path.suffix != ".rrd":
            raise UsageError(f"{path}: expected a results directory or a rerun recording (.rrd)")
        return [path]
    if not path.is_dir():
        raise UsageError(f"{path}: no such results directory or recording")
    found = sorted([*path.glob("view.rrd"), *path.glob("view/*.rrd")])
    if not found:
        raise UsageError(f"{path}: no recorded view (view.rrd or view/*.rrd); record one with fimnav launch --view or fimnav montecarlo --view")
    return found


def run(args: argparse.Namespace) -> int:
    """Serve the recordings until interrupted."""
    from missions.launch.liveview import ViewServer, require_rerun

    files = recordings(args.results)
    require_rerun()
    with ViewServer(web_port=args.port, rrds=files) as server:
        print(f"view: {server.browser_url}  ({', '.join(str(f) for f in files)}; Ctrl-C to stop)", flush=True)
        code = server.wait()
    print(f"rerun's viewer stopped (status {code})", file=sys.stderr)
    return 1
