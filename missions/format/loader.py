"""Load a mission YAML file into one frozen :class:`missions.format.schema.Mission`, or fail with one
clear message.

Every failure (missing file, YAML syntax, a non-mapping document, a wrong type, an unknown
key, an impossible value) raises :class:`MissionError`, a :class:`comms.errors.UsageError`
(exit status 2), whose message names the file, the line when known, the key path
(``drones.roles[3]``), what was expected and what was found, and for a mistyped key the
nearest valid key. The YAML is read with PyYAML's safe loader only.

A mission argument is a path when that file exists, else the name of a mission shipped in
the package (``paper/joint``; see :func:`bundled_missions` and :func:`resolve_mission`).
"""

from __future__ import annotations

import copy
import difflib
import importlib.resources
import os
import re
import unicodedata
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from comms.errors import UsageError
from missions.format.schema import Mission, Start

#: Mission files larger than this are refused (a mission is a few kilobytes).
MAX_FILE_BYTES: int = 1 << 20
#: YAML node visits allowed (with aliases expanded): stops "billion laughs" documents.
MAX_NODES: int = 200_000
#: At most this many problems are listed in one message.
MAX_PROBLEMS: int = 10
#: Folders of the ``missions`` package whose ``*.yaml`` files are bundled missions, named
#: ``<folder>/<stem>`` (``paper/joint``).
BUNDLED_FOLDERS: tuple[str, ...] = ("paper",)

_OVERRIDE_LABEL = "override"


class MissionError(UsageError):
    """A mission that cannot be used: the message says where, what was expected and found.

    Attributes:
        file: the mission file (or ``"<string>"``) the error is about.
        problems: one line per problem, each ``[line N: ]key.path: expected ..., found ...``.
    """

    def __init__(self, file: str, problems: Sequence[str]) -> None:
        self.file = file
        self.problems = tuple(problems)
        if len(self.problems) == 1:
            message = f"{file}: {self.problems[0]}"
        else:
            listed = "\n".join(f"  - {p}" for p in self.problems[:MAX_PROBLEMS])
            more = len(self.problems) - MAX_PROBLEMS
            tail = f"\n  ... and {more} more" if more > 0 else ""
            message = f"{file}: {len(self.problems)} problems in the mission:\n{listed}{tail}"
        super().__init__(message)


# --- public API ----------------------------------------------------------------------------


def load_mission(path: str | os.PathLike[str], overrides: Mapping[str, Any] | None = None) -> Mission:
    """Read, check and return the mission in ``path``.

    Args:
        path: the mission YAML file, or when no such file exists the name of a bundled
            mission (``paper/joint``, ``paper/joint.yaml``, ``missions/paper/joint.yaml``; see
            :func:`resolve_mission`). Relative file paths inside the mission (TLS
            certificates, signing keys) are resolved against its directory. Messages name the
            mission as given here.
        overrides: values that replace the file's, applied before validation. Keys are
            dotted key paths (``"constraints.activation"``) or nested mappings
            (``{"constraints": {"activation": "paper"}}``); e.g. ``{"criterion": "D"}``.

    Raises:
        MissionError: the file is missing or unreadable, not YAML, not a mapping, or not a
            valid mission (see ``docs/mission-format.md``).
    """
    label = os.fspath(path)
    file, text = _read_mission_file(path)
    return loads_mission(text, file=label, base_dir=file.resolve().parent, overrides=overrides)


def read_mission_text(path: str | os.PathLike[str]) -> str:
    """The text of the mission file (or bundled mission) ``path`` names, unparsed.

    Raises:
        MissionError: no such file or bundled mission, a directory, a file over
            :data:`MAX_FILE_BYTES`, an unreadable file, or text that is not UTF-8.
    """
    return _read_mission_file(path)[1]


def bundled_missions() -> dict[str, Path]:
    """The missions shipped in the ``missions`` package: name (``paper/joint``) -> file, by name.

    Found with :mod:`importlib.resources`, so they are found for an installed and an editable
    install alike, from any working directory.
    """
    root = importlib.resources.files("missions")
    found: dict[str, Path] = {}
    for folder in BUNDLED_FOLDERS:
        directory = root.joinpath(folder)
        if not directory.is_dir():
            continue
        for entry in directory.iterdir():
            if entry.name.endswith(".yaml") and entry.is_file() and isinstance(entry, os.PathLike):
                found[f"{folder}/{entry.name[: -len('.yaml')]}"] = Path(os.fspath(entry))
    return dict(sorted(found.items()))


def resolve_mission(path: str | os.PathLike[str]) -> Path:
    """The file a mission argument names.

    ``path`` itself when it exists (a file, or anything else, which :func:`load_mission`
    then refuses); else the bundled mission of that name: ``paper/joint``,
    ``paper/joint.yaml`` and the source-tree path ``missions/paper/joint.yaml`` all name
    ``missions/paper/joint.yaml`` inside the installed package. Otherwise ``path`` unchanged
    (it does not exist).
    """
    given = Path(path)
    try:
        if given.exists():
            return given
    except (OSError, ValueError):  # a name too long, a NUL in the path: not an existing file
        return given
    return bundled_missions().get(_bundled_name(os.fspath(path)), given)


def suggest_bundled(name: str, limit: int = 3) -> list[str]:
    """Bundled mission names close to ``name`` (a mistyped name or path), nearest first.

    The file name is compared with the bundled files' names in the same folder (any folder
    when ``name`` has none, or names a folder with no close match): ``paper/jiont`` ->
    ``paper/joint``, ``heterogeneous`` -> ``paper/heterogeneous``."""
    wanted = _bundled_name(name)
    folder, _, stem = wanted.rpartition("/")
    by_stem: dict[str, list[str]] = {}
    for bundled in bundled_missions():
        bundled_folder, _, bundled_stem = bundled.rpartition("/")
        if not folder or folder == bundled_folder:
            by_stem.setdefault(bundled_stem, []).append(bundled)
    close = difflib.get_close_matches(stem, list(by_stem), n=limit, cutoff=0.6)
    if not close and folder:  # a folder that does not exist: look in every folder
        return suggest_bundled(stem, limit)
    return [n for s in close for n in by_stem[s]][:limit]


def _bundled_name(text: str) -> str:
    """The bundled-mission name a mission argument would be (``./missions/paper/joint.yaml``
    -> ``paper/joint``)."""
    name = text.replace("\\", "/")
    while name.startswith("./"):
        name = name[2:]
    if name.startswith("missions/"):
        name = name[len("missions/") :]
    for suffix in (".yaml", ".yml"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


def _not_found(label: str) -> str:
    """The one-line problem for a mission argument that is neither a file nor a bundled name."""
    close = suggest_bundled(label)
    hint = f"; did you mean {' or '.join(close)}?" if close else ""
    return f"mission not found: expected an existing YAML file or the name of a bundled mission (fimnav missions list), found neither{hint}"


def _read_mission_file(path: str | os.PathLike[str]) -> tuple[Path, str]:
    """Resolve ``path`` (:func:`resolve_mission`) and return the file and its UTF-8 text."""
    label = os.fspath(path)
    p = resolve_mission(path)
    try:
        if not p.exists():
            raise MissionError(label, [_not_found(label)])
        if not p.is_file():
            raise MissionError(label, ["expected a mission YAML file, found a directory or special file"])
        size = p.stat().st_size
        if size > MAX_FILE_BYTES:
            raise MissionError(label, [f"expected a mission file of at most {MAX_FILE_BYTES} bytes, found {size} bytes"])
        raw = p.read_bytes()
    except MissionError:
        raise
    except OSError as exc:
        raise MissionError(label, [f"expected a readable file, found that it cannot be read: {exc.strerror or exc}"]) from None
    except ValueError as exc:  # e.g. a NUL in the path
        raise MissionError(label, [f"expected a file path, found one that cannot be used: {exc}"]) from None
    try:
        return p, raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line_start = raw.rfind(b"\n", 0, exc.start) + 1
        line = raw.count(b"\n", 0, exc.start) + 1
        column = len(raw[line_start : exc.start].decode("utf-8", errors="replace")) + 1
        raise MissionError(
            label,
            [
                f"line {line}, column {column}: expected UTF-8 text, found the invalid byte 0x{raw[exc.start]:02x} "
                f"(byte offset {exc.start}; save the file as UTF-8)"
            ],
        ) from None


def loads_mission(
    text: str,
    *,
    file: str = "<string>",
    base_dir: str | Path | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> Mission:
    """Like :func:`load_mission` for YAML ``text``; ``file`` names it in messages and
    ``base_dir`` resolves relative paths (default: left relative)."""
    node, data = _parse_yaml(text, file)
    override_paths: list[tuple[str | int, ...]] = []
    if overrides:
        data = _apply_overrides(data, overrides, file, override_paths)
    context = {"base_dir": str(base_dir)} if base_dir is not None else None
    try:
        return Mission.model_validate(data, context=context)
    except ValidationError as exc:
        errors = _merge_typos(exc.errors(include_url=False))
        problems = [_describe(err, node, override_paths) for err in errors]
        raise MissionError(file, problems) from None


def mission_to_yaml(mission: Mission) -> str:
    """The mission as run, every default filled in, as YAML that :func:`loads_mission` reads
    back into an equal :class:`Mission` (for results directories)."""
    data = mission.model_dump(mode="json")
    # Exactly one start form is present in a valid mission; write only that one.
    data["drones"]["start"] = {k: v for k, v in data["drones"]["start"].items() if v is not None}
    body = yaml.dump(data, Dumper=_MissionDumper, sort_keys=False, allow_unicode=True, width=100)
    header = f"# fimnav mission {mission.id!r} as run (format version {mission.schema_version}); every default filled in.\n"
    return header + body


class _MissionDumper(yaml.SafeDumper):
    """Safe YAML dumper writing lists of scalars inline (``[0.0, 150.0, 8.0]``), the rest in block
    style, and text holding a YAML line break other than ``\\n`` double-quoted (escaped)."""

    def represent_list(self, data: Iterable[Any]) -> yaml.SequenceNode:  # PyYAML hook
        flow = all(not isinstance(item, (list, dict)) for item in data)
        return self.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)

    def represent_text(self, data: str) -> yaml.Node:  # PyYAML hook
        # With allow_unicode PyYAML writes NEL, LS and PS raw in plain and single-quoted text,
        # and reads them back as line breaks (folded to a space): escape them instead.
        if any(ch in data for ch in "\x85\u2028\u2029"):
            return self.represent_scalar("tag:yaml.org,2002:str", data, style='"')
        return self.represent_str(data)


_MissionDumper.add_representer(list, _MissionDumper.represent_list)
_MissionDumper.add_representer(str, _MissionDumper.represent_text)


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """Parse command-line ``KEY=VALUE`` items (``constraints.activation=paper``) into an
    overrides mapping for :func:`load_mission`; VALUE is read as YAML (``3``, ``[1, 2]``).

    Raises:
        MissionError: an item without ``=`` or with a value that is not YAML.
    """
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*", key):
            raise MissionError("--set", [f"expected KEY=VALUE with a dotted key such as constraints.activation=paper, found {item!r}"])
        try:
            out[key] = yaml.safe_load(value) if value.strip() else ""
        except yaml.YAMLError:
            raise MissionError("--set", [f"{key}: expected a YAML value, found {value!r}"]) from None
    return out


# --- YAML ----------------------------------------------------------------------------------


class _MissionLoader(yaml.SafeLoader):
    """PyYAML's safe loader, whose value constructors fail with the value's position.

    A scalar with an explicit tag that does not fit it (``!!bool maybe``, ``!!timestamp x``,
    ``!!int ''``, an integer too long to convert) makes PyYAML's constructors raise plain
    Python errors without a position; here they become :class:`_UnreadableValue` at the node.
    """

    def construct_object(self, node: yaml.Node, deep: bool = False) -> Any:  # PyYAML hook
        try:
            return super().construct_object(node, deep=deep)
        except (ValueError, OverflowError, TypeError, KeyError, AttributeError, IndexError) as exc:
            raise _UnreadableValue(node, exc) from None

    def fetch_flow_collection_start(self, TokenClass: Any) -> None:  # PyYAML hook
        """Refuse a ``[`` or ``{`` deeper than :data:`MAX_FLOW_DEPTH` at once: PyYAML's scanner
        takes time quadratic in the depth (a 10 kB file of 5000 nested ``[`` took 3 s to reach
        Python's recursion limit), and no mission nests more than a few levels."""
        if self.flow_level >= MAX_FLOW_DEPTH:
            raise _TooDeep(self.get_mark())
        super().fetch_flow_collection_start(TokenClass)


#: The deepest nesting of flow collections (``[ ]``, ``{ }``) a mission file may have.
MAX_FLOW_DEPTH: int = 64


class _TooDeep(yaml.YAMLError):
    """Flow collections nested deeper than :data:`MAX_FLOW_DEPTH`, at ``mark``."""

    def __init__(self, mark: yaml.Mark) -> None:
        super().__init__()
        self.mark = mark


class _UnreadableValue(yaml.constructor.ConstructorError):
    """A YAML value its tag's constructor cannot read; :attr:`problem` is the message."""

    def __init__(self, node: yaml.Node, exc: Exception) -> None:
        tag = node.tag.replace("tag:yaml.org,2002:", "!!")
        if isinstance(node, yaml.ScalarNode):
            value = node.value
        elif isinstance(node, (yaml.SequenceNode, yaml.MappingNode)):
            value = f"a {node.id}"
        else:  # PyYAML composes only scalars, sequences and mappings
            value = f"a {type(node).__name__}"
        reason = str(exc).split(";")[0] if isinstance(exc, (ValueError, OverflowError)) else ""
        found = _short(value) + (f" ({reason})" if reason else "")
        super().__init__(None, None, f"expected a YAML value that can be read as {tag}, found {found}"[:300], node.start_mark)


def _parse_yaml(text: str, file: str) -> tuple[yaml.Node, dict[str, Any]]:
    """Compose (for line numbers) and construct one YAML document with the safe loader.

    Every PyYAML failure (reader, scanner, parser, composer, constructor) and every value
    that cannot be read becomes one :class:`MissionError` naming the position."""
    loader: _MissionLoader | None = None
    try:
        loader = _MissionLoader(text)  # the reader refuses control characters here
        node = loader.get_single_node()
        if node is None:
            raise MissionError(file, ["expected a mapping of mission keys (id, drones, source, ...), found an empty document"])
        _check_nodes(node, file)
        data = loader.construct_document(node)
    except _TooDeep as exc:
        raise MissionError(
            file, [f"line {exc.mark.line + 1}: expected a mission, found YAML nested too deeply (more than {MAX_FLOW_DEPTH} levels of [ ] or {{ }})"]
        ) from None
    except yaml.reader.ReaderError as exc:
        raise MissionError(file, [_describe_reader_error(exc, text)]) from None
    except yaml.MarkedYAMLError as exc:
        raise MissionError(file, [_describe_yaml_error(exc, text)]) from None
    except yaml.YAMLError as exc:
        raise MissionError(file, [f"expected valid YAML, found {' '.join(str(exc).split())}"]) from None
    except MissionError:
        raise
    except (ValueError, OverflowError, TypeError) as exc:  # a value outside any node (safety net)
        reason = str(exc).split(";")[0]
        raise MissionError(file, [f"expected YAML values that can be read, found one that cannot: {reason}"[:300]]) from None
    except RecursionError:
        raise MissionError(file, ["expected a mission, found YAML nested too deeply"]) from None
    finally:
        if loader is not None:
            loader.dispose()
    if not isinstance(data, dict):
        raise MissionError(
            file,
            [f"line {node.start_mark.line + 1}: expected a mapping of mission keys (id, drones, source, ...) at the top level, found {_kind(data)}"],
        )
    return node, data


def _line_column(text: str, index: int) -> tuple[int, int]:
    """1-based line and column of character ``index`` of ``text``, counting line breaks as
    PyYAML does (``\\n``, ``\\r\\n``, a lone ``\\r``, NEL, LS, PS)."""
    before = text[:index]
    line = 1 + len(re.findall("\r\n|[\n\r\x85\u2028\u2029]", before))
    last_break = max(before.rfind(ch) for ch in "\n\r\x85\u2028\u2029")
    return line, index - last_break


def _describe_reader_error(exc: yaml.reader.ReaderError, text: str) -> str:
    """``line L, column C: expected printable text, found the control character U+0000 (NUL)``."""
    line, column = _line_column(text, exc.position)
    code = exc.character if isinstance(exc.character, int) else ord(str(exc.character)[:1] or "\0")
    category = unicodedata.category(chr(code))
    if category == "Cc":
        names = {0x00: "NUL", 0x07: "BEL", 0x08: "BS", 0x0B: "VT", 0x0C: "FF", 0x1B: "ESC", 0x7F: "DEL"}
        kind = "the control character"
        name = f" ({names[code]})" if code in names else ""
    else:
        kind, name = "the character", " (not allowed in YAML)"
    return (
        f"line {line}, column {column}: invalid YAML: expected printable text (no control characters "
        f"but tab and line breaks), found {kind} U+{code:04X}{name}"
    )


#: PyYAML errors about a construct that was opened and never closed, by their context: the
#: position reported is where the construct started, the line of the mistake.
_UNCLOSED: tuple[tuple[str, str], ...] = (
    ("while parsing a flow sequence", "the list '[' started here"),
    ("while parsing a flow mapping", "the mapping '{' started here"),
    ("while scanning a quoted scalar", "the quoted text started here"),
    ("while scanning a simple key", "the key"),
)


def _at(mark: yaml.Mark) -> str:
    return f"line {mark.line + 1}, column {mark.column + 1}"


def _token(text: str) -> str:
    """A PyYAML token name in words: ``'<stream end>'`` -> ``the end of the file``."""
    words = {
        "'<stream end>'": "the end of the file",
        "<stream end>": "the end of the file",
        "'<block end>'": "the end of the block",
        "'<block mapping start>'": "a key indented differently",
        "'<block sequence start>'": "a list item indented differently",
        "'<scalar>'": "a value",
        "'<document start>'": "a document separator '---'",
        "'<document end>'": "a document end '...'",
    }
    return words.get(text.strip(), text.strip())


def _describe_yaml_error(exc: yaml.MarkedYAMLError, text: str) -> str:
    """``line L, column C: invalid YAML: ...expected ..., found ...`` from a PyYAML error.

    The position is the line of the mistake: where an unclosed bracket, brace, quote or key
    started (PyYAML's ``context_mark``) rather than where the parser gave up
    (``problem_mark``, lines later); for every other error, the problem's position."""
    problem = " ".join((exc.problem or "").split())
    context = " ".join((exc.context or "").split())
    problem_mark, context_mark = exc.problem_mark, exc.context_mark
    if isinstance(exc, _UnreadableValue):
        return f"{_at(problem_mark)}: {problem}" if problem_mark is not None else problem
    for opening, what in _UNCLOSED:
        if context.startswith(opening) and context_mark is not None and problem_mark is not None:
            if "quoted" in opening:
                quote = text[context_mark.index] if 0 <= context_mark.index < len(text) else "quote"
                if problem.startswith("found unexpected "):
                    expected = f"a closing {quote}"
                    found = problem[len("found unexpected ") :]
                    found = {"end of stream": "the end of the file", "document separator": "a document separator"}.get(found, found)
                    return (
                        f"{_at(context_mark)}: invalid YAML: {what} with {quote} is not closed: expected {expected}, "
                        f"found {found} at {_at(problem_mark)}"
                    )
                break
            if "simple key" in opening:
                return f"{_at(context_mark)}: invalid YAML: expected 'key: value' on this line, found no ':' after the key"
            for but in (", but got ", ", but found "):
                if problem.startswith("expected") and but in problem:
                    head, tail = problem.split(but, 1)
                    return f"{_at(context_mark)}: invalid YAML: {what} is not closed: {head}, found {_token(tail)} at {_at(problem_mark)}"
    mark = problem_mark or context_mark
    where = f"{_at(mark)}: " if mark is not None else ""
    if isinstance(exc, yaml.constructor.ConstructorError) and "tag" in problem:
        tag = problem.rsplit(" ", 1)[-1].strip("'").replace("tag:yaml.org,2002:", "!!")
        return f"{where}invalid YAML: expected plain data (standard tags, no language-specific ones), found the tag {tag}"
    if problem.startswith("found undefined alias"):
        name = problem.rsplit(" ", 1)[-1].strip("'")
        return f"{where}invalid YAML: expected an anchor &{name} defined before the alias *{name}, found none"
    if context.startswith("found duplicate anchor") and context_mark is not None:
        name = context.split("'")[1] if context.count("'") >= 2 else "?"
        return f"{where}invalid YAML: expected each anchor once, found &{name} again (first at {_at(context_mark)})"
    if problem.startswith("found unknown escape character"):
        char = problem.rsplit(" ", 1)[-1]
        return (
            f"{where}invalid YAML: expected an escape sequence such as \\\\ or \\n in double-quoted text "
            f"(or single quotes, where a backslash is plain), found the unknown escape \\{char.strip(chr(39))}"
        )
    if problem == "found unhashable key":
        return f"{where}invalid YAML: expected a text key, found a list or mapping used as a key"
    if problem.startswith("found character '\\t'"):
        return f"{where}invalid YAML: expected spaces for indentation (YAML allows no tabs there), found a tab character"
    if problem == "mapping values are not allowed here":
        return (
            f"{where}invalid YAML: expected a key indented like the keys above it (or a value containing ': ' "
            f"in quotes), found ':' where a mapping is not allowed"
        )
    in_context = ""
    if context and context_mark is not None and context_mark is not mark:
        in_context = f" ({context} started at {_at(context_mark)})"
    elif context:
        in_context = f" ({context})"
    if problem.startswith("expected <block end>, but found ") and context.startswith("while parsing a block"):
        found = _token(problem[len("expected <block end>, but found ") :])
        if found in ("']'", "'}'"):
            return f"{where}invalid YAML{in_context}: expected a key, an item or the end of the block, found {found} that closes nothing"
        return (
            f"{where}invalid YAML{in_context}: expected a line indented like an enclosing block's keys or items, "
            f"found {found} (check the indentation)"
        )
    for but in (", but got ", " but got ", ", but found ", " but found "):
        if problem.startswith("expected") and but in problem:
            head, tail = problem.split(but, 1)
            return f"{where}invalid YAML{in_context}: {head}, found {_token(tail)}"
    if context.startswith("expected") and problem.startswith("but found "):
        return f"{where}invalid YAML: {context}, found {problem[len('but found ') :]}"
    if problem.startswith("found "):
        problem = problem[len("found ") :]
    return f"{where}invalid YAML{in_context}: expected valid YAML syntax, found {problem}"


def _check_nodes(root: yaml.Node, file: str) -> None:
    """Refuse duplicate keys and documents that expand to too many nodes (alias bombs)."""
    stack = [root]
    visits = 0
    while stack:
        node = stack.pop()
        visits += 1
        if visits > MAX_NODES:
            raise MissionError(file, [f"expected a mission of at most {MAX_NODES} YAML nodes, found more (alias expansion?)"])
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, int] = {}
            for key, value in node.value:
                if isinstance(key, yaml.ScalarNode):
                    if key.value in seen:
                        raise MissionError(
                            file,
                            [
                                f"line {key.start_mark.line + 1}: {key.value}: expected each key once in a mapping, "
                                f"found it again (first at line {seen[key.value]})"
                            ],
                        )
                    seen[key.value] = key.start_mark.line + 1
                stack.append(key)
                stack.append(value)
        elif isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)


def _node_at(root: yaml.Node, parts: Sequence[str | int]) -> tuple[yaml.Node, bool]:
    """The YAML node at ``parts`` (or the deepest existing ancestor) and whether it was found.

    For a mapping key, the key node is returned (its line is where the user typed it)."""
    node = root
    for depth, part in enumerate(parts):
        nxt = None
        if isinstance(node, yaml.MappingNode):
            for key, value in node.value:
                if isinstance(key, yaml.ScalarNode) and key.value == str(part):
                    nxt = key if depth == len(parts) - 1 else value
                    break
        elif isinstance(node, yaml.SequenceNode) and isinstance(part, int) and 0 <= part < len(node.value):
            nxt = node.value[part]
        if nxt is None:
            return node, False
        node = nxt
    return node, True


# --- overrides -----------------------------------------------------------------------------


def _apply_overrides(data: dict[str, Any], overrides: Mapping[str, Any], file: str, paths: list[tuple[str | int, ...]]) -> dict[str, Any]:
    """Deep-merge ``overrides`` (dotted keys or nested mappings) into a copy of ``data``."""
    out = copy.deepcopy(data)

    def merge(target: dict[str, Any], key_parts: list[str], value: Any, prefix: tuple[str, ...]) -> None:
        head, rest = key_parts[0], key_parts[1:]
        here = prefix + (head,)
        if rest:
            child = target.setdefault(head, {})
            if not isinstance(child, dict):
                raise MissionError(
                    file, [f"{_join(here)}: expected a mapping to apply override {'.'.join(here + tuple(rest))!r}, found {_kind(child)}"]
                )
            merge(child, rest, value, here)
        elif isinstance(value, Mapping) and isinstance(target.get(head), dict):
            for k, v in value.items():
                merge(target[head], str(k).split("."), v, here)
        else:
            target[head] = copy.deepcopy(value)
            paths.append(here)

    for key, value in overrides.items():
        merge(out, str(key).split("."), value, ())
    _one_formation(out, paths)
    return out


def _one_formation(data: dict[str, Any], paths: Sequence[tuple[str | int, ...]]) -> None:
    """A start formation set by an override (``--set drones.start.rows.spacing_m=4``) replaces
    the file's other one (``drones.start.ellipse``): a start has exactly one
    (:attr:`missions.format.schema.Start.FORMATIONS`); two set by overrides stay, and fail."""
    drones = data.get("drones")
    start = drones.get("start") if isinstance(drones, dict) else None
    if not isinstance(start, dict) or {("drones",), ("drones", "start")} & set(paths):
        return  # no start, or all of it from an override
    chosen = {str(p[2]) for p in paths if len(p) >= 3 and p[:2] == ("drones", "start")} & set(Start.FORMATIONS)
    if chosen:
        for name in set(Start.FORMATIONS) - chosen:
            start.pop(name, None)


# --- error messages ------------------------------------------------------------------------

_TYPE_NAMES = {
    str: "text",
    bool: "a boolean",
    int: "an integer",
    float: "a number",
    type(None): "null",
    list: "a list",
    tuple: "a list",
    dict: "a mapping",
}


def _kind(value: Any) -> str:
    name = _TYPE_NAMES.get(type(value), type(value).__name__)
    if isinstance(value, (dict, list, tuple)):
        return name if not value else f"{name} {_short(value)}"
    if value is None:
        return "null (an empty value)"
    return f"{_short(value)} ({name})"


def _short(value: Any, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _join(parts: Iterable[str | int]) -> str:
    out = ""
    for part in parts:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def _split(path: str) -> list[str | int]:
    parts: list[str | int] = []
    for name, index in re.findall(r"([^.\[\]]+)|\[(\d+)\]", path):
        parts.append(int(index) if index else name)
    return parts


def _model_fields_at(parts: Sequence[str | int]) -> list[str] | None:
    """Names of the keys valid in the mapping at ``parts`` (ints skipped), or None."""
    model: Any = Mission
    for part in parts:
        if isinstance(part, int):
            continue
        if not (isinstance(model, type) and issubclass(model, BaseModel)) or part not in model.model_fields:
            return None
        model = _inner_model(model.model_fields[part].annotation)
    if isinstance(model, type) and issubclass(model, BaseModel):
        return sorted(model.model_fields)
    return None


def _inner_model(annotation: Any) -> Any:
    """The BaseModel inside ``X``, ``X | None`` or ``tuple[X, ...]``, else the annotation."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()) or ():
        found = _inner_model(arg)
        if isinstance(found, type) and issubclass(found, BaseModel):
            return found
    return annotation


def _expected_from_msg(msg: str) -> str:
    for prefix in ("Input should be ", "Value should be "):
        if msg.startswith(prefix):
            rest = msg[len(prefix) :]
            if rest.startswith(("greater", "less")):
                rest = "a number " + rest
            return rest.replace("a valid tuple", "a list").replace("a valid dictionary", "a mapping")
    return msg[:1].lower() + msg[1:]


def _merge_typos(errors: Sequence[Any]) -> list[Any]:
    """Drop a "missing key" error when an unknown key beside it is a typo of that key: the
    user wrote one wrong key, so report one problem (the unknown key, with the suggestion)."""
    typos: set[tuple[Any, ...]] = set()
    for err in errors:
        if err["type"] == "extra_forbidden":
            parent = tuple(err["loc"][:-1])
            valid = _model_fields_at(list(parent)) or []
            for close in difflib.get_close_matches(str(err["loc"][-1]), valid, n=1, cutoff=0.6):
                typos.add(parent + (close,))
    return [e for e in errors if not (e["type"] == "missing" and tuple(e["loc"]) in typos)]


def _describe(err: Mapping[str, Any], root: yaml.Node, override_paths: Sequence[tuple[str | int, ...]]) -> str:
    """One line for one pydantic error: ``line N: key.path: expected ..., found ...``."""
    loc: list[str | int] = list(err["loc"])
    kind = err["type"]
    ctx = err.get("ctx") or {}
    if kind == "mission_invalid" and ctx.get("path"):
        loc += _split(str(ctx["path"]))
    if kind == "extra_forbidden":
        key = str(loc[-1])
        valid = _model_fields_at(loc[:-1]) or []
        close = difflib.get_close_matches(key, valid, n=1, cutoff=0.6)
        if close:
            text = f"unknown key, did you mean {close[0]!r}? expected one of {', '.join(valid)}; found {key!r}"
        else:
            text = f"unknown key; expected one of {', '.join(valid)}; found {key!r}"
    elif kind == "invalid_key":
        bad_key = loc.pop() if loc else None
        valid = _model_fields_at(loc) or []
        text = f"unknown key; expected text keys (one of {', '.join(valid)}); found {_kind(bad_key)}"
    elif kind == "missing":
        parent_fields = _model_fields_at(loc[:-1])
        if parent_fields is not None:
            text = "expected this required key, found it missing"
        else:
            text = f"expected an item at index {loc[-1]}, found it missing"
    elif kind in ("mission_invalid", "vector3", "mavlink_connection"):
        text = err["msg"]
    elif kind == "string_pattern_mismatch":
        text = f"expected text matching the pattern {ctx.get('pattern')}, found {_kind(err.get('input'))}"
    elif kind == "model_type" or kind == "dict_type":
        text = f"expected a mapping (key: value lines), found {_kind(err.get('input'))}"
    else:
        text = f"expected {_expected_from_msg(err['msg'])}, found {_kind(err.get('input'))}"

    from_override = any(tuple(loc[: len(p)]) == p for p in override_paths)
    if from_override:
        where = f"({_OVERRIDE_LABEL}) "
    else:
        node, _found = _node_at(root, loc)
        where = f"line {node.start_mark.line + 1}: "
    return f"{where}{_join(loc)}: {text}"
