"""Regenerate the broken-mission corpus tests/missions/broken/*.yaml.

Run ``python tests/missions/make_broken_corpus.py``. Each file starts with comment lines
``# expect-path:``, ``# expect-expected:`` and ``# expect-found:`` that
``test_missions_broken.py`` checks against the message of ``fimnav check``. The base mission
is valid; each case breaks exactly one thing.
"""
from pathlib import Path

BASE = """\
id: broken_case
seed: 3
dt_s: 1.0
steps: 20
trials: 2
criterion: A
drones:
  count: 4
  roles: [ranging, bearing, joint, ranging]
  start:
    positions_m:
      - [0.0, 150.0, 8.0]
      - [10.0, 150.0, 8.0]
      - [20.0, 150.0, 8.0]
      - [30.0, 150.0, 8.0]
source:
  position_m: [0.0, 0.0, 2.0]
obstacles:
  - {name: B1, min_m: [-20.0, 80.0, 0.0], max_m: [20.0, 100.0, 30.0]}
constraints:
  speed_min_mps: 0.5
  speed_max_mps: 1.0
  z_min_m: 2.0
  z_max_m: 25.0
"""

def sub(old, new, text=BASE):
    assert old in text, old
    return text.replace(old, new, 1)

C = {}
def case(name, what, path, expected, found, text):
    C[name] = (what, path, expected, found, text)

case("wrong_type_count", "drones.count is text", "drones.count", "a valid integer", "'ten'",
     sub("  count: 4", "  count: ten"))
case("wrong_type_dt", "dt_s is text", "dt_s", "a valid number", "'fast'", sub("dt_s: 1.0", "dt_s: fast"))
case("wrong_type_bool_as_number", "trials: yes is a boolean, not a count", "trials", "a valid integer", "True",
     sub("trials: 2", "trials: yes"))
case("wrong_type_float_as_int", "steps must be an integer", "steps", "a valid integer", "20.5",
     sub("steps: 20", "steps: 20.5"))
case("wrong_type_section", "constraints must be a mapping", "constraints", "a mapping", "a list",
     sub("""constraints:
  speed_min_mps: 0.5
  speed_max_mps: 1.0
  z_min_m: 2.0
  z_max_m: 25.0
""", "constraints: [0.5, 1.0]\n"))
case("typo_top_level_key", "constraint instead of constraints", "constraint", "one of", "'constraint'",
     sub("constraints:\n", "constraint:\n"))
case("typo_nested_key", "activtion instead of activation", "constraints.activtion", "one of", "'activtion'",
     sub("  z_max_m: 25.0\n", "  z_max_m: 25.0\n  activtion: paper\n"))
case("typo_drone_key", "cuont instead of count", "drones.cuont", "one of", "'cuont'",
     sub("  count: 4", "  cuont: 4"))
case("missing_source", "no source section", "source", "required key", "missing",
     sub("source:\n  position_m: [0.0, 0.0, 2.0]\n", ""))
case("missing_id", "no mission id", "id", "required key", "missing", sub("id: broken_case\n", ""))
case("missing_start", "drones without start", "drones.start", "required key", "missing",
     sub("""  start:
    positions_m:
      - [0.0, 150.0, 8.0]
      - [10.0, 150.0, 8.0]
      - [20.0, 150.0, 8.0]
      - [30.0, 150.0, 8.0]
""", ""))
case("speed_min_above_max", "v_min > v_max", "constraints.speed_min_mps", "speed_min_mps <= speed_max_mps", "2",
     sub("  speed_min_mps: 0.5", "  speed_min_mps: 2.0"))
case("z_min_above_max", "z_min > z_max", "constraints.z_min_m", "z_min_m <= z_max_m", "30",
     sub("  z_min_m: 2.0", "  z_min_m: 30.0"))
case("start_inside_obstacle", "drone 2 starts inside B1", "drones.start.positions_m[1]", "outside every obstacle",
     "inside obstacle 'B1'", sub("      - [10.0, 150.0, 8.0]", "      - [10.0, 90.0, 8.0]"))
case("start_near_obstacle", "drone 2 starts 2 m from B1 (d_O* = 5 m)", "drones.start.positions_m[1]",
     "at least d_obstacle_m = 5 m", "2 m from obstacle 'B1'",
     sub("      - [10.0, 150.0, 8.0]", "      - [10.0, 102.0, 8.0]"))
case("starts_too_close", "drones 2 and 3 start 0.5 m apart (d_U* = 1 m)", "drones.start.positions_m[2]",
     "at least d_uav_m = 1 m apart", "drones 2 and 3 0.5 m apart",
     sub("      - [20.0, 150.0, 8.0]", "      - [10.5, 150.0, 8.0]"))
case("start_too_close_to_source", "drone 1 starts 30 m from the source (d_S* = 50 m)",
     "drones.start.positions_m[0]", "at least d_source_m = 50 m", "drone 1",
     sub("      - [0.0, 150.0, 8.0]", "      - [0.0, 30.0, 8.0]"))
case("start_below_z_min", "drone 4 starts below z_min", "drones.start.positions_m[3]", "z within [z_min_m, z_max_m]",
     "drone 4 at [30, 150, 1]", sub("      - [30.0, 150.0, 8.0]", "      - [30.0, 150.0, 1.0]"))
case("start_outside_fence", "drone 4 starts outside the fence", "drones.start.positions_m[3]", "inside the fence",
     "drone 4", sub("trials: 2\n", "trials: 2\nfence: {x_min_m: -100.0, x_max_m: 25.0, y_min_m: -100.0, y_max_m: 200.0}\n"))
case("role_unknown", "a role that does not exist", "drones.roles[3]", "'ranging', 'bearing' or 'joint'", "'sonar'",
     sub("[ranging, bearing, joint, ranging]", "[ranging, bearing, joint, sonar]"))
case("role_string_unknown", "one role string for all, misspelt", "drones.roles", "one of 'ranging', 'bearing', 'joint'",
     "'rangin'", sub("[ranging, bearing, joint, ranging]", "rangin"))
case("role_not_text", "a role given as a number", "drones.roles[1]", "'ranging', 'bearing' or 'joint'", "2",
     sub("[ranging, bearing, joint, ranging]", "[ranging, 2, joint, ranging]"))
case("role_count_mismatch", "3 roles for 4 drones", "drones.roles", "4 roles", "3 roles",
     sub("[ranging, bearing, joint, ranging]", "[ranging, bearing, joint]"))
case("positions_count_mismatch", "5 drones, 4 positions", "drones.start.positions_m", "5 positions", "4 positions",
     sub("  count: 4\n  roles: [ranging, bearing, joint, ranging]", "  count: 5\n  roles: joint"))
case("count_zero", "no drones", "drones.count", "greater than or equal to 1", "0", sub("  count: 4", "  count: 0"))
case("both_start_forms", "positions and ellipse together", "drones.start", "exactly one of 'positions_m', 'ellipse' or 'rows'",
     "'positions_m' and 'ellipse'", sub("  start:\n", "  start:\n    ellipse: {center_m: [0.0, 150.0, 8.0], radius_x_m: 20.0, radius_z_m: 5.0}\n"))
case("vector_wrong_length", "a 2D source position", "source.position_m", "3 numbers [x, y, z]", "2 items",
     sub("  position_m: [0.0, 0.0, 2.0]", "  position_m: [0.0, 0.0]"))
case("nan_value", "a NaN bearing std", "channel.sigma_bearing_deg", "a finite number", "nan",
     sub("constraints:\n", "channel:\n  sigma_bearing_deg: .nan\nconstraints:\n"))
case("negative_sigma", "a negative shadowing ratio", "channel.sigma_ratio_los", "greater than 0", "-1.7",
     sub("constraints:\n", "channel:\n  sigma_ratio_los: -1.7\nconstraints:\n"))
case("box_min_not_below_max", "an obstacle with min z above max z", "obstacles[0].max_m[2]", "max_m[2] > min_m[2]", "30",
     sub("max_m: [20.0, 100.0, 30.0]", "max_m: [20.0, 100.0, 30.0]").replace("min_m: [-20.0, 80.0, 0.0]", "min_m: [-20.0, 80.0, 40.0]"))
case("duplicate_obstacle_name", "two obstacles called B1", "obstacles[1].name", "not used by another obstacle", "B1",
     sub("obstacles:\n", "obstacles:\n  - {name: B1, min_m: [50.0, 50.0, 0.0], max_m: [60.0, 60.0, 30.0]}\n"))
case("source_inside_obstacle", "the source inside B1", "source.position_m", "outside every obstacle", "obstacle 'B1'",
     sub("  position_m: [0.0, 0.0, 2.0]", "  position_m: [0.0, 90.0, 2.0]").replace("      - [0.0, 150.0, 8.0]", "      - [0.0, 150.0, 8.0]"))
case("source_moves_out_of_fence", "a source that leaves the fence", "source", "inside the fence", "at t = 20 s",
     sub("  position_m: [0.0, 0.0, 2.0]", "  position_m: [0.0, 0.0, 2.0]\n  velocity_mps: [100.0, 0.0, 0.0]"))
case("criterion_unknown", "criterion E", "criterion", "'A' or 'D'", "'E'", sub("criterion: A", "criterion: E"))
case("bad_mission_id", "an id that cannot be a Zenoh key chunk", "id", "pattern", "'my mission/1'",
     sub("id: broken_case", "id: my mission/1"))
case("bad_connection", "a MAVLink connection string pymavlink cannot use", "vehicles.overrides[0].connection",
     "pymavlink connection string", "'udp://localhost'",
     sub("trials: 2\n", "trials: 2\nvehicles:\n  overrides:\n    - {connection: 'udp://localhost'}\n    - {}\n    - {}\n    - {}\n"))
case("overrides_count_mismatch", "two vehicle overrides for four drones", "vehicles.overrides", "0 or 4 entries",
     "2 entries", sub("trials: 2\n", "trials: 2\nvehicles:\n  overrides: [{}, {flavour: px4}]\n"))
case("zenoh_unknown_mode", "zenoh mode 'server'", "zenoh.mode", "'peer', 'client' or 'router'", "'server'",
     sub("trials: 2\n", "trials: 2\nzenoh: {mode: server}\n"))
case("duplicate_key", "steps given twice", "steps", "each key once", "again", sub("trials: 2\n", "trials: 2\nsteps: 30\n"))
case("bad_yaml_syntax", "an unclosed bracket (reported where it opens)", "line 21, column 15", "',' or ']'", "':'", sub("  position_m: [0.0, 0.0, 2.0]", "  position_m: [0.0, 0.0, 2.0"))
case("bad_yaml_tab", "a tab used for indentation", "line 12, column 1", "spaces for indentation", "a tab character", sub("  count: 4", "\tcount: 4"))
case("not_a_mapping", "a list at the top level", "line 5", "a mapping of mission keys", "a list", "- id: x\n- drones: 3\n")
case("scalar_document", "a bare string", "line 5", "a mapping of mission keys", "'just some text'", "just some text\n")
case("empty_document", "an empty file (comments only)", "", "a mapping of mission keys", "an empty document", "")
case("multiple_documents", "two YAML documents", "line 29", "a single document", "another document", BASE + "---\n" + BASE)
case("alias_bomb", "a billion-laughs alias expansion", "", "at most 200000 YAML nodes", "found more",
     "a: &a [x, x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
     "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b, *b]\nd: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c, *c]\n"
     "e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d, *d]\nf: &f [*e, *e, *e, *e, *e, *e, *e, *e, *e, *e]\n"
     "g: [*f, *f, *f, *f, *f, *f, *f, *f, *f, *f]\n")
case("python_tag", "an unsafe YAML tag", "line 5, column 5", "no language-specific ones", "!!python/object", "id: !!python/object/apply:os.system ['echo pwned']\n" + BASE[len("id: broken_case\n"):])

case("huge_integer", "an integer too long to read", "line 6, column 7", "a YAML value that can be read as !!int", "4300 digits",
     sub("seed: 3", "seed: " + "9" * 5000))
case("binary_id", "a !!binary (bytes) mission id", "id", "a valid string", "b'x'", sub("id: broken_case", "id: !!binary eA=="))
case("integer_key", "a number used as a key", "constraints", "text keys", "3 (an integer)",
     sub("  z_max_m: 25.0\n", "  z_max_m: 25.0\n  3: x\n"))
case("deep_nesting", "lists nested 5000 deep", "", "a mission", "nested too deeply",
     sub("trials: 2\n", "trials: 2\ndescription: " + "[" * 5000 + "]" * 5000 + "\n"))
case("recursive_alias", "a list that contains itself", "", "at most 200000 YAML nodes", "found more",
     sub("trials: 2\n", "trials: 2\ndescription: &loop [*loop]\n"))
case("infinite_value", "an infinite speed", "constraints.speed_max_mps", "a finite number", "inf",
     sub("  speed_max_mps: 1.0", "  speed_max_mps: .inf"))

# Every kind of PyYAML error (reader, scanner, parser, composer, constructor): one line, the
# position of the mistake (for an unclosed bracket, brace or quote: where it opens).
case("control_nul", "a NUL byte in otherwise valid UTF-8 (yaml.reader)", "line 10, column 18", "printable text",
     "U+0000 (NUL)", sub("trials: 2\n", "trials: 2\ndescription: lost\x00byte\n"))
case("control_escape", "a terminal escape sequence in a text value (yaml.reader)", "line 10, column 14", "printable text",
     "U+001B (ESC)", sub("trials: 2\n", "trials: 2\ndescription: \x1b[31mred\x1b[0m\n"))
case("unclosed_double_quote", "a double quote never closed (yaml.scanner)", "line 10, column 14", "a closing \"",
     "the end of the file", sub("trials: 2\n", "trials: 2\ndescription: \"never closed\n"))
case("unclosed_single_quote", "a single quote never closed (yaml.scanner)", "line 10, column 14", "a closing '",
     "the end of the file", sub("trials: 2\n", "trials: 2\ndescription: 'never closed\n"))
case("bad_escape", "a Windows path in double quotes (yaml.scanner)", "line 10, column 18", "an escape sequence",
     "unknown escape \\p", sub("trials: 2\n", "trials: 2\ndescription: \"C:\\path\\mission\"\n"))
case("missing_colon", "a key without ':' (yaml.scanner)", "line 8, column 1", "'key: value'", "no ':'",
     sub("steps: 20", "steps 20"))
case("indent_too_deep", "a key indented one space deeper than its siblings (yaml.scanner)", "line 26, column 17",
     "a key indented like the keys above it", "':'", sub("  speed_max_mps: 1.0", "   speed_max_mps: 1.0"))
case("indent_too_shallow", "a key indented one space less than its siblings (yaml.parser)", "line 26, column 2",
     "a line indented like", "a key indented differently", sub("  speed_max_mps: 1.0", " speed_max_mps: 1.0"))
case("list_item_misaligned", "a start position indented less than the others (yaml.parser)", "line 18, column 6",
     "a line indented like", "a list item indented differently", sub("      - [20.0, 150.0, 8.0]", "     - [20.0, 150.0, 8.0]"))
case("unclosed_brace", "an obstacle's '{' never closed (yaml.parser)", "line 23, column 5", "',' or '}'", "a value at line 24",
     sub("max_m: [20.0, 100.0, 30.0]}", "max_m: [20.0, 100.0, 30.0]"))
case("unclosed_bracket_at_end", "a '[' never closed at the end of the file (yaml.parser)", "line 29, column 14",
     "',' or ']'", "the end of the file", BASE.replace("trials: 2\n", "") + "trials: 2\ndescription: [never, closed\n")
case("stray_bracket", "a ']' that closes nothing (yaml.parser)", "line 13, column 44", "the end of the block",
     "']' that closes nothing", sub("[ranging, bearing, joint, ranging]", "[ranging, bearing, joint, ranging]]"))
case("undefined_alias", "an alias with no anchor (yaml.composer)", "line 10, column 14", "an anchor &nope",
     "none", sub("trials: 2\n", "trials: 2\ndescription: *nope\n"))
case("duplicate_anchor", "the same anchor twice (yaml.composer)", "line 10, column 7", "each anchor once",
     "&s again", sub("trials: 2\n", "trials: 2\ndescription: &s one\nseed: &s 4\n").replace("seed: 3\n", ""))
case("unknown_tag", "a tag YAML does not define (yaml.constructor)", "line 10, column 12", "standard tags",
     "!!foo", sub("criterion: A", "criterion: !!foo A"))
case("list_as_key", "a list used as a key (yaml.constructor)", "line 10, column 3", "a text key",
     "a list or mapping used as a key", sub("trials: 2\n", "trials: 2\n? [x, y]\n: 1\n"))
case("bad_bool_tag", "!!bool on a value that is not a boolean", "line 9, column 9", "read as !!bool", "'maybe'",
     sub("trials: 2", "trials: !!bool maybe"))
case("bad_timestamp_tag", "!!timestamp on a value that is not a date", "line 10, column 14", "read as !!timestamp",
     "'yesterday'", sub("trials: 2\n", "trials: 2\ndescription: !!timestamp yesterday\n"))
case("empty_int_tag", "!!int on an empty value", "line 8, column 8", "read as !!int", "''", sub("steps: 20", "steps: !!int ''"))

out = Path(__file__).resolve().parent / "broken"
for name, (what, path, expected, found, text) in C.items():
    header = (f"# Broken mission: {what}.\n# expect-path: {path}\n# expect-expected: {expected}\n"
              f"# expect-found: {found}\n")
    (out / f"{name}.yaml").write_text(header + text)
# not UTF-8: header lines, then an invalid byte
(out / "not_utf8.yaml").write_bytes(b"# Broken mission: not UTF-8 text.\n# expect-path: line 5, column 8\n"
                                     b"# expect-expected: UTF-8 text\n# expect-found: invalid byte 0xe9\nid: caf\xe9\n")
print(len(C) + 1, "files")
