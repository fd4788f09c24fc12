"""Malformed mission files: one line naming the file, the position of the mistake and what was
wrong, exit status 2, never a traceback.

The position is checked against the line that holds the mistake (marked ``# <- mistake`` in
the texts below): for an unclosed bracket, brace or quote that is where it opens, not where
PyYAML gives up lines later.
"""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from missions.cli.main import main
from missions.format.loader import MAX_FILE_BYTES, MAX_FLOW_DEPTH, MissionError, load_mission, loads_mission

PAPER = Path(__file__).resolve().parents[2] / "missions" / "paper"

#: name -> (YAML text with the mistake's line marked "# <- mistake", words the message must hold)
MISTAKES: dict[str, tuple[str, tuple[str, ...]]] = {
    "unclosed_bracket": (
        "id: m\nsteps: 3\nsource:\n  position_m: [0.0, 0.0, 2.0   # <- mistake\nconstraints:\n  z_min_m: 2.0\n",
        ("the list '[' started here is not closed", "expected ',' or ']'", "found a value at line 5, column 1"),
    ),
    "unclosed_bracket_many_lines": (
        "id: m\nobstacles: [{name: B1, min_m: [0, 0, 0], max_m: [1, 1, 1]},   # <- mistake\n"
        "  {name: B2, min_m: [5, 5, 0], max_m: [6, 6, 1]}\n\nsteps: 3\n",
        ("the list '[' started here is not closed", "found a value at line 5"),
    ),
    "unclosed_brace": (
        "id: m\nsource: {position_m: [0, 0, 2]   # <- mistake\nsteps: 3\n",
        ("the mapping '{' started here is not closed", "expected ',' or '}'"),
    ),
    "unclosed_double_quote": (
        'id: m\ndescription: "a mission  # <- mistake\nsteps: 3\nseed: 1\n',
        ('the quoted text started here with " is not closed', 'expected a closing "', "found the end of the file"),
    ),
    "unclosed_single_quote": (
        "id: m\ndescription: 'a mission  # <- mistake\nsteps: 3\nseed: 1\n",
        ("the quoted text started here with ' is not closed", "expected a closing '", "found the end of the file"),
    ),
    "indent_too_shallow": (
        "id: m\ndrones:\n  count: 4\n roles: joint   # <- mistake\nsteps: 3\n",
        ("expected a line indented like", "found a key indented differently", "check the indentation"),
    ),
    "indent_too_deep": (
        "id: m\ndrones:\n  count: 4\n   roles: joint   # <- mistake\nsteps: 3\n",
        ("expected a key indented like the keys above it", "found ':'"),
    ),
    "list_item_misaligned": (
        "id: m\ndrones:\n  start:\n    positions_m:\n      - [0, 0, 1]\n     - [0, 0, 2]   # <- mistake\nsteps: 3\n",
        ("expected a line indented like", "found a list item indented differently"),
    ),
    "tab_indent": (
        "id: m\ndrones:\n\tcount: 4   # <- mistake\n",
        ("expected spaces for indentation", "found a tab character"),
    ),
    "missing_colon": (
        "id: m\nsteps 3   # <- mistake\nseed: 1\n",
        ("expected 'key: value' on this line", "found no ':'"),
    ),
    "no_space_after_colon": (
        "id: m\ndescription: a: b   # <- mistake\nseed: 1\n",
        ("or a value containing ': ' in quotes", "found ':'"),
    ),
    "bad_escape": (
        'id: m\ndescription: "C:\\path"   # <- mistake\n',
        ("expected an escape sequence", "found the unknown escape \\p"),
    ),
    "undefined_alias": ("id: m\ndescription: *nope   # <- mistake\n", ("expected an anchor &nope", "found none")),
    "duplicate_anchor": (
        "id: &a m\ndescription: &a x   # <- mistake\n",
        ("expected each anchor once", "found &a again (first at line 1, column 5)"),
    ),
    "unknown_tag": ("id: m\ncriterion: !!foo A   # <- mistake\n", ("standard tags", "found the tag !!foo")),
    "python_tag": ("id: m\nseed: !!python/object/apply:os.getpid []   # <- mistake\n", ("found the tag !!python/object/apply",)),
    "bad_bool_tag": ("id: m\ntrials: !!bool maybe   # <- mistake\n", ("read as !!bool", "found 'maybe'")),
    "bad_timestamp_tag": ("id: m\ndescription: !!timestamp soon   # <- mistake\n", ("read as !!timestamp", "found 'soon'")),
    "empty_int_tag": ("id: m\nseed: !!int ''   # <- mistake\n", ("read as !!int", "found ''")),
    "list_as_key": ("id: m\n? [a, b]   # <- mistake\n: 1\n", ("expected a text key", "found a list or mapping")),
    "control_nul": ("id: m\nseed: 1\x00   # <- mistake\n", ("expected printable text", "found the control character U+0000 (NUL)")),
    "control_escape": ("id: m\ndescription: \x1b[1mbold   # <- mistake\n", ("found the control character U+001B (ESC)",)),
}


def _mistake_line(text: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), start=1) if "# <- mistake" in line)


@pytest.mark.parametrize("name", sorted(MISTAKES))
def test_yaml_error_points_at_the_line_of_the_mistake(name: str) -> None:
    text, words = MISTAKES[name]
    with pytest.raises(MissionError) as info:
        loads_mission(text, file="mission.yaml")
    message = str(info.value)
    assert "\n" not in message, message
    found = re.match(r"mission\.yaml: line (\d+), column (\d+): ", message)
    assert found, message
    assert int(found.group(1)) == _mistake_line(text), message
    assert "expected" in message and "found" in message, message
    assert message.index("expected") < message.rindex("found"), message
    for word in words:
        assert word in message, (word, message)


def test_unclosed_bracket_reported_where_it_opens_with_the_column() -> None:
    text = "id: m\nsteps: 3\nsource:\n  position_m: [0.0, 0.0, 2.0\n\n\nconstraints:\n  z_min_m: 2.0\n"
    with pytest.raises(MissionError) as info:
        loads_mission(text, file="mission.yaml")
    assert str(info.value).startswith("mission.yaml: line 4, column 15: invalid YAML: the list '[' started here is not closed")
    assert "at line 7, column 12" in str(info.value)


def _check(target: Path | str) -> tuple[int, str, str]:
    """``fimnav check TARGET`` through the CLI entry point: (status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["check", str(target)])
    return code, out.getvalue(), err.getvalue()


def _assert_one_line_error(code: int, out: str, err: str, file: Path) -> str:
    assert code == 2, (code, err)
    assert out == "" and "Traceback" not in err
    message = err.strip()
    assert "\n" not in message and message.startswith(f"fimnav check: error: {file}: "), message
    assert "expected" in message and "found" in message, message
    return message


def test_nul_byte_in_valid_utf8_is_one_line_with_position(tmp_path: Path) -> None:
    mission = tmp_path / "mission.yaml"
    mission.write_bytes((PAPER / "joint.yaml").read_bytes().replace(b"id: paper_joint", b"id: paper_\x00joint"))
    message = _assert_one_line_error(*_check(mission), mission)
    line = mission.read_bytes().split(b"\n").index(b"id: paper_\x00joint") + 1
    assert f"line {line}, column 11: " in message and "U+0000 (NUL)" in message


def test_not_utf8_names_the_line_column_and_byte(tmp_path: Path) -> None:
    mission = tmp_path / "latin1.yaml"
    mission.write_bytes("id: m\ndescription: Café\n".encode("latin-1"))
    message = _assert_one_line_error(*_check(mission), mission)
    assert "line 2, column 17: expected UTF-8 text, found the invalid byte 0xe9" in message


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"", "found an empty document"),
        (b"# only a comment\n", "found an empty document"),
        (b"- a\n- b\n", "found a list"),
        (b"42\n", "found 42 (an integer)"),
        (b"id: a\nid: b\n", "line 2: id: expected each key once in a mapping, found it again (first at line 1)"),
        (b"id: a\n---\nid: b\n", "a single document"),
        (b"\xef\xbb\xbfid: m\n", "drones: expected this required key"),  # a BOM is fine; the mission is incomplete
    ],
    ids=["zero_bytes", "comments_only", "list", "scalar", "duplicate_key", "two_documents", "utf8_bom"],
)
def test_malformed_file_is_one_clear_error(tmp_path: Path, content: bytes, words: str) -> None:
    mission = tmp_path / "m.yaml"
    mission.write_bytes(content)
    code, out, err = _check(mission)
    assert code == 2 and out == "" and "Traceback" not in err, err
    assert err.startswith(f"fimnav check: error: {mission}: ") and words in err, err


def test_huge_file_is_refused_before_reading(tmp_path: Path) -> None:
    mission = tmp_path / "huge.yaml"
    mission.write_bytes(b"id: m\n" + b"# padding\n" * (MAX_FILE_BYTES // 10 + 1))
    message = _assert_one_line_error(*_check(mission), mission)
    assert f"expected a mission file of at most {MAX_FILE_BYTES} bytes" in message


@pytest.mark.parametrize("opening", ["[", "{a: "])
def test_flow_nesting_past_the_limit_is_refused_at_its_line(opening: str) -> None:
    """``[`` or ``{`` nested one level past :data:`MAX_FLOW_DEPTH` is refused where it opens;
    at the limit the nesting is read, and the mission refused for what the value is (a list
    where a text is expected), not for its depth."""
    closing = "]" if opening == "[" else "}"

    def nested(depth: int) -> str:
        return "id: m\nsteps: 3\n\ndescription: " + opening * depth + "1" + closing * depth + "\n"

    with pytest.raises(MissionError) as too_deep:
        loads_mission(nested(MAX_FLOW_DEPTH + 1))
    assert f"line 4: expected a mission, found YAML nested too deeply (more than {MAX_FLOW_DEPTH} levels" in str(too_deep.value)
    with pytest.raises(MissionError) as at_limit:
        loads_mission(nested(MAX_FLOW_DEPTH))
    assert "nested too deeply" not in str(at_limit.value) and "description" in str(at_limit.value)


def test_directory_is_refused(tmp_path: Path) -> None:
    message = _assert_one_line_error(*_check(tmp_path), tmp_path)
    assert "expected a mission YAML file, found a directory" in message


_VALID = (PAPER / "heterogeneous.yaml").read_text(encoding="utf-8")


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    at=st.integers(min_value=0, max_value=len(_VALID)),
    cut=st.integers(min_value=0, max_value=8),
    insert=st.text(alphabet=st.sampled_from(list("[]{}:,'\"-?&*!|>#%@`\t\n \x00\x1b\\é")), max_size=4),
)
def test_any_edit_of_a_mission_loads_or_is_a_mission_error(at: int, cut: int, insert: str) -> None:
    """Cutting characters out of a valid mission and typing YAML punctuation in their place
    never raises anything but :class:`MissionError` (whose message names the file)."""
    text = _VALID[:at] + insert + _VALID[at + cut:]
    try:
        loads_mission(text, file="edited.yaml")
    except MissionError as exc:
        assert str(exc).startswith("edited.yaml: "), str(exc)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=200))
def test_any_bytes_load_or_are_a_mission_error(tmp_path_factory: pytest.TempPathFactory, data: bytes) -> None:
    mission = tmp_path_factory.mktemp("bytes") / "m.yaml"
    mission.write_bytes(data)
    with pytest.raises(MissionError):
        load_mission(mission)
