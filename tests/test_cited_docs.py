"""The code stands on the repository's own docs: every Markdown file a module of the packages
cites (``docs/distributed.md``, ``README.md``, a bare ``DESIGN.md``) exists in the repository."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("planner", "comms", "vehicle_sim", "missions")
CITATION = re.compile(r"(?<![\w/.-])([\w/.-]+\.md)\b")


def cited(text: str) -> set[str]:
    """The Markdown paths named in ``text``."""
    return set(CITATION.findall(text))


def test_every_cited_doc_exists() -> None:
    missing = sorted(
        f"{path.relative_to(ROOT)}: {name}"
        for package in PACKAGES
        for path in (ROOT / package).rglob("*.py")
        for name in cited(path.read_text(encoding="utf-8"))
        if not (ROOT / name).is_file()
    )
    assert missing == []


def test_the_scan_sees_a_citation() -> None:
    assert cited('"""Frames (DESIGN.md): ... see docs/distributed.md, "The launcher"."""') == {"DESIGN.md", "docs/distributed.md"}
