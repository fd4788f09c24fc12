"""Load a mission YAML file into one frozen :class:`missions.schema.Mission`, or fail with one
clear message.

Every failure (missing file, YAML syntax, a non-mapping document, a wrong type, an unknown
key, an impossible value) raises :class:`MissionError`, a :class:`planner.errors.UsageError`
(exit status 2), whose message names the file, the line when known, the key path
(``drones.roles[3]``), what was expected and what was found, and for a mistyped key the
nearest valid key. The YAML is read with PyYAML's safe loader only.
"""

from __future__ import annotations

import copy
import difflib
import re
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from missions.schema import Mission
from planner.errors import UsageError

#: Mission files larger than this are refused (a mission is a few kilobytes).
MAX_FILE_BYTES: int = 1 << 20
#: YAML node visits allowed (with aliases expanded): stops "billion laughs" documents.
MAX_NODES: int = 200_000
#: At most this many problems are listed in one message.
MAX_PROBLEMS: int = 10

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


def load_mission(path: str | Path, overrides: Mapping[str, Any] | None = None) -> Mission:
    """Read, check and return the mission in ``path``.

    Args:
        path: the mission YAML file. Relative file paths inside it (TLS certificates,
            signing keys) are resolved against its directory.
        overrides: values that replace the file's, applied before validation. Keys are
            dotted key paths (``"constraints.activation"``) or nested mappings
            (``{"constraints": {"activation": "paper"}}``); e.g. ``{"criterion": "D"}``.

    Raises:
        MissionError: the file is missing or unreadable, not YAML, not a mapping, or not a
            valid mission (see ``docs/mission-format.md``).
    """
    p = Path(path)
    label = str(path)
    try:
        if not p.exists():
            raise MissionError(label, ["mission file not found (expected an existing YAML file)"])
        if not p.is_file():
            raise MissionError(label, ["expected a mission YAML file, found a directory or special file"])
        size = p.stat().st_size
        if size > MAX_FILE_BYTES:
            raise MissionError(label, [f"expected a mission file of at most {MAX_FILE_BYTES} bytes, found {size} bytes"])
        raw = p.read_bytes()
    except OSError as exc:
        raise MissionError(label, [f"cannot read the file: {exc.strerror or exc}"]) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MissionError(label, [f"expected UTF-8 text, found an invalid byte at offset {exc.start}"]) from None
    return loads_mission(text, file=label, base_dir=p.resolve().parent, overrides=overrides)


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
    header = (
        f"# fimnav mission {mission.id!r} as run (format version {mission.schema_version}); "
        "every default filled in.\n"
    )
    return header + body


class _MissionDumper(yaml.SafeDumper):
    """Safe YAML dumper writing lists of scalars inline (``[0.0, 150.0, 8.0]``), the rest in block style."""

    def represent_list(self, data: list[Any]) -> yaml.Node:  # noqa: D102 - PyYAML hook
        flow = all(not isinstance(item, (list, dict)) for item in data)
        return self.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_MissionDumper.add_representer(list, _MissionDumper.represent_list)


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


def _parse_yaml(text: str, file: str) -> tuple[yaml.Node, dict[str, Any]]:
    """Compose (for line numbers) and construct one YAML document with the safe loader."""
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            raise MissionError(file, ["expected a mapping of mission keys (id, drones, source, ...), found an empty document"])
        _check_nodes(node, file)
        data = loader.construct_document(node)
    except yaml.MarkedYAMLError as exc:
        raise MissionError(file, [_describe_yaml_error(exc)]) from None
    except yaml.YAMLError as exc:
        raise MissionError(file, [f"invalid YAML: {exc}"]) from None
    except MissionError:
        raise
    except (ValueError, OverflowError, TypeError) as exc:  # e.g. an integer of > 4300 digits
        reason = str(exc).split(";")[0]
        raise MissionError(file, [f"expected YAML values that can be read, found one that cannot: {reason}"[:300]]) from None
    except RecursionError:
        raise MissionError(file, ["expected a mission, found YAML nested too deeply"]) from None
    finally:
        loader.dispose()
    if not isinstance(data, dict):
        raise MissionError(
            file,
            [f"line {node.start_mark.line + 1}: expected a mapping of mission keys (id, drones, source, ...) "
             f"at the top level, found {_kind(data)}"],
        )
    return node, data


def _describe_yaml_error(exc: yaml.MarkedYAMLError) -> str:
    """``line L, column C: invalid YAML: expected ..., found ...`` from a PyYAML error."""
    mark = exc.problem_mark or exc.context_mark
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    problem = (exc.problem or "").strip()
    context = f" ({exc.context.strip()})" if exc.context else ""
    if isinstance(exc, yaml.constructor.ConstructorError) and "tag" in problem:
        tag = problem.rsplit(" ", 1)[-1]
        return f"{where}invalid YAML: expected plain data (no language-specific tags), found the tag {tag}"
    for but in (", but got ", " but got ", ", but found ", " but found "):
        if problem.startswith("expected") and but in problem:
            head, tail = problem.split(but, 1)
            return f"{where}invalid YAML{context}: {head}, found {tail}"
    if exc.context and exc.context.startswith("expected") and problem.startswith("but found "):
        return f"{where}invalid YAML: {exc.context.strip()}, found {problem[len('but found '):]}"
    if problem.startswith("found "):
        problem = problem[len("found "):]
    return f"{where}invalid YAML{context}: expected valid YAML syntax, found {problem}"


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
                            [f"line {key.start_mark.line + 1}: {key.value}: expected each key once in a mapping, "
                             f"found it again (first at line {seen[key.value]})"],
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


def _apply_overrides(
    data: dict[str, Any], overrides: Mapping[str, Any], file: str, paths: list[tuple[str | int, ...]]
) -> dict[str, Any]:
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
    return out


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
            rest = msg[len(prefix):]
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
    loc: list[str | int] = [p for p in err["loc"]]
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
        key = loc.pop() if loc else None
        valid = _model_fields_at(loc) or []
        text = f"unknown key; expected text keys (one of {', '.join(valid)}); found {_kind(key)}"
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
