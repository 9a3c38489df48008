"""Frame logs (docs/wire.md, "Frame logs (JSON lines)"): simulated frames survive the round trip to
the bit with their ground truth dropped, every malformed line or log is a FrameLogError naming the
line and the field, and fuzzing proves that nothing else escapes and that whatever parses also
formats back to the same frame.
"""

from __future__ import annotations

import copy
import dataclasses
import json
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.models import SensorFrame
from protocol.errors import LocalProtocolError
from protocol.framelog import (
    FrameLogError,
    format_frame_line,
    format_header,
    parse_frame_line,
    read_frame_log,
)
from protocol.frames import FrameLimits
from sim.loader import load_scenario
from sim.sensors import Simulator
from tests.protocol import fuzz
from tests.protocol.fuzz import FUZZ
from tests.protocol.test_frames import (
    BASE_FRAMES,
    NO_TRUTH,
    REF,
    REF_LOCAL,
    REF_NONE,
    assert_same_frame,
    make_frame,
)

PAPER = load_scenario("paper")
SEEDS = (0, 1, 5, 11)
REF_LINE = format_frame_line(REF)
REF_DOC: dict[str, Any] = json.loads(REF_LINE)


def _without_truth(frame: SensorFrame) -> SensorFrame:
    return dataclasses.replace(frame, true_pose=NO_TRUTH.copy())


def _line(doc: Any) -> str:
    return json.dumps(doc, separators=(",", ":"))


def _with(path: fuzz.Path, value: Any) -> str:
    return _line(fuzz.set_at(copy.deepcopy(REF_DOC), path, value))


def _log(frames: list[SensorFrame]) -> list[str]:
    return [format_header(), *(format_frame_line(f) for f in frames)]


def assert_log_error(call: Any, line: int, field: str, says: str) -> None:
    """``call()`` raises a FrameLogError of ``line`` and ``field`` whose message says ``says``."""
    with pytest.raises(FrameLogError) as caught:
        call()
    got = caught.value
    assert (got.line, got.field) == (line, field), repr(got)
    assert str(got).startswith(f"line {line}: {field}: "), str(got)
    assert says in str(got), str(got)


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("seed", SEEDS)
def test_framelog_round_trip_simulated_frames_drops_truth(seed: int) -> None:
    sim = Simulator(PAPER, seed)
    for robot in PAPER.robot_ids:
        frames = sim.frames(robot)
        got = read_frame_log(_log(frames))
        assert len(got) == len(frames) == PAPER.steps
        for g, f in zip(got, frames, strict=True):
            assert np.isfinite(f.true_pose).all()  # the simulator has it; the log must not
            assert_same_frame(g, _without_truth(f))


@pytest.mark.parametrize("index", range(len(BASE_FRAMES)))
def test_framelog_round_trip_is_bit_exact(index: int) -> None:
    """−0.0, subnormals, 1e300 and 2³²−1 ids come back to the bit; the line re-formats equal."""
    frame = BASE_FRAMES[index]
    line = format_frame_line(frame)
    got = parse_frame_line(line, 1)
    assert_same_frame(got, _without_truth(frame))
    assert format_frame_line(got) == line


def test_framelog_line_holds_the_documented_keys_and_no_truth() -> None:
    doc = json.loads(format_frame_line(REF))
    assert list(doc) == ["robot", "k", "odometry", "detections"]
    assert [list(d) for d in doc["detections"]] == [["id", "z_geo", "z_sem"]] * 3
    assert doc["odometry"] == REF.odometry.tolist()
    assert "truth" not in REF_LINE and "true" not in REF_LINE
    assert not any(repr(float(x)) in REF_LINE for x in REF.true_pose)
    partial = dataclasses.replace(REF, true_pose=np.array([np.nan, 1.0, 2.0]))
    assert format_frame_line(partial) == REF_LINE  # a truth is dropped unread, however odd
    assert json.loads(format_header()) == {"v": 1, "type": "frame_log"}


def test_framelog_states_ids_only_when_not_global() -> None:
    assert "ids" not in REF_DOC  # a log of global ids reads as every log written before
    local = json.loads(format_frame_line(REF_LOCAL))
    assert local["ids"] == "local" and [d["id"] for d in local["detections"]] == [4, 2**32 - 1, 0]
    none = json.loads(format_frame_line(REF_NONE))
    assert none["ids"] == "none"
    assert [list(d) for d in none["detections"]] == [["z_geo", "z_sem"]] * 3
    assert parse_frame_line(_line({**REF_DOC, "ids": "global"}), 1).ids == "global"


@pytest.mark.parametrize(
    ("doc", "field", "says"),
    [
        ({**REF_DOC, "ids": "tracker"}, "ids", "'tracker': expected one of 'global', 'local'"),
        ({**REF_DOC, "ids": 1}, "ids", "expected a string, got int"),
        ({**REF_DOC, "ids": "none"}, "detections[0]", "unknown keys ['id']"),
        ({**json.loads(format_frame_line(REF_NONE)), "ids": "local"}, "detections[0]", "missing"),
    ],
)
def test_parse_frame_line_refuses_a_malformed_id_kind(doc: Any, field: str, says: str) -> None:
    assert_log_error(lambda: parse_frame_line(_line(doc), 3), 3, field, says)


def test_read_frame_log_holds_one_id_kind() -> None:
    frames = _frames()
    frames[2] = dataclasses.replace(frames[2], ids="local")
    assert_log_error(lambda: read_frame_log(_log(frames)), 4, "ids", "line 2 holds 'global' ids")


def test_framelog_header_is_optional_and_blank_lines_are_skipped() -> None:
    frames = Simulator(PAPER, 3).frames("r1")[:4]
    lines = [format_frame_line(f) for f in frames]
    assert len(read_frame_log(lines)) == 4
    with_blanks = ["", format_header(), "  ", lines[0], lines[1], "\n", lines[2], lines[3] + "\n"]
    assert [f.k for f in read_frame_log(with_blanks)] == [1, 2, 3, 4]
    gap = [format_header(), "", lines[0], "", lines[2]]  # the gap is on line 5
    assert_log_error(lambda: read_frame_log(gap), 5, "k", "expected 2")


def test_format_frame_line_refuses_what_a_reader_would() -> None:
    bad = dataclasses.replace(REF, odometry=np.array([0.0, np.inf, 0.0]))
    with pytest.raises(LocalProtocolError, match="odo: non-finite"):
        format_frame_line(bad)
    with pytest.raises(LocalProtocolError, match="det: 3 > 2"):
        format_frame_line(REF, FrameLimits(max_detections=2))


# --------------------------------------------------------------------------- one line


DET = ("detections", 0)
LINE_ERRORS: list[tuple[str, str, str]] = [
    (_with(("odometry", 2), 1e999), "odometry", "non-finite number"),
    (REF_LINE.replace("0.25", "NaN", 1), "odometry", "non-finite number"),
    (_with((*DET, "z_sem", 1), float("inf")), "detections[0].z_sem", "non-finite number"),
    (_with((*DET, "z_geo", 0), -float("inf")), "detections[0].z_geo", "non-finite number"),
    (_with(("odometry", 1), "0.5"), "odometry", "expected numbers only"),
    (_with(("odometry", 1), True), "odometry", "expected numbers only"),
    (_with(("odometry", 1), 10**400), "odometry", "number out of range"),
    (_with(("odometry",), [0.0, 1.0]), "odometry", "expected 3 numbers, got 2"),
    (_with(("odometry",), {"x": 1}), "odometry", "expected an array of numbers"),
    (_with((*DET, "z_geo"), [1, 2, 3, 4]), "detections[0].z_geo", "4 numbers: 3 (x, y, θ"),
    # a point's (bearing, range) first: the next detection, a pose's, is of another kind
    (_with((*DET, "z_geo"), [1, 2]), "detections[1].z_geo", "detections are of one kind"),
    (_with((*DET, "z_sem"), []), "detections[0].z_sem", "at least one score"),
    (_with((*DET, "z_sem"), [0.5] * 65), "detections[0].z_sem", "65 scores > 64"),
    (_with(("detections", 1, "z_sem"), [0.5, 0.5]), "detections[1].z_sem", "first detection"),
    (_with((*DET, "id"), -1), "detections[0].id", "outside 0..4294967295"),
    (_with((*DET, "id"), 2**32), "detections[0].id", "outside"),
    (_with((*DET, "id"), 4.0), "detections[0].id", "expected an integer"),
    (_with(("detections", 2, "id"), 4), "detections[2].id", "duplicate object id 4"),
    (_with((*DET, "class"), 1), "detections[0]", "unknown keys ['class']"),
    (_with(("detections",), 7), "detections", "expected an array"),
    (_with(("detections",), [1]), "detections[0]", "expected a map"),
    (_with(("k",), 0), "k", "outside 1.."),
    (_with(("k",), 2**63), "k", "outside 1.."),
    (_with(("k",), "7"), "k", "expected an integer"),
    (_with(("robot",), "r 1"), "robot", "invalid robot id"),
    (_with(("robot",), None), "robot", "expected a string"),
    (_with(("truth",), [1.0, 2.0, 3.0]), "frame", "unknown keys ['truth']"),
    (_line({k: v for k, v in REF_DOC.items() if k != "k"}), "frame", "missing keys ['k']"),
    ("[1, 2]", "frame", "expected a map"),
    ("", "json", "not JSON"),
    (REF_LINE[:-3], "json", "not JSON"),
    ('{"k": 1, "k": 2}', "json", "duplicate key 'k'"),
    ("[" * 100_000, "json", "nested too deeply"),
]


@pytest.mark.parametrize(("line", "field", "says"), LINE_ERRORS, ids=[e[2] for e in LINE_ERRORS])
def test_parse_frame_line_names_line_and_field(line: str, field: str, says: str) -> None:
    assert_log_error(lambda: parse_frame_line(line, 12), 12, field, says)


def test_parse_frame_line_applies_the_frame_limits() -> None:
    say = "expected 2 scores, got 3"
    assert_log_error(
        lambda: parse_frame_line(REF_LINE, 4, FrameLimits(num_classes=2)),
        4,
        "detections[0].z_sem",
        say,
    )
    assert_log_error(
        lambda: parse_frame_line(REF_LINE, 4, FrameLimits(max_detections=2)),
        4,
        "detections",
        "3 > 2",
    )
    small = FrameLimits(max_message_bytes=60)  # refused unparsed: 4 characters per wire byte
    assert len(REF_LINE) > 4 * 60
    assert_log_error(lambda: parse_frame_line(REF_LINE, 4, small), 4, "json", "characters > 240")
    short = _line({"robot": "r1", "k": 1, "odometry": [0, 0, 0], "detections": []})
    assert len(short) < 60  # the line fits, its 69 wire bytes do not
    assert_log_error(lambda: parse_frame_line(short, 1, small), 1, "frame", "69 bytes > 60")
    assert parse_frame_line(short, 1, FrameLimits(max_message_bytes=69)).k == 1


def test_parse_frame_line_refuses_a_non_text_line() -> None:
    assert_log_error(lambda: parse_frame_line(b"{}", 3), 3, "json", "expected text, got bytes")  # type: ignore[arg-type]


# --------------------------------------------------------------------------- whole logs


def _frames(robot: str = "r1", steps: int = 4) -> list[SensorFrame]:
    return Simulator(PAPER, 2).frames(robot)[:steps]


def test_read_frame_log_needs_consecutive_steps_from_1() -> None:
    frames = _frames()
    assert_log_error(lambda: read_frame_log(_log(frames[1:])), 2, "k", "expected 1")
    shuffled = [frames[0], frames[2], frames[1], frames[3]]
    assert_log_error(lambda: read_frame_log(_log(shuffled)), 3, "k", "expected 2")
    repeated = [frames[0], frames[1], frames[1]]
    assert_log_error(lambda: read_frame_log(_log(repeated)), 4, "k", "expected 3, got 2")


def test_read_frame_log_holds_one_robot() -> None:
    mixed = [*_frames("r1", 2), _frames("r2", 3)[2]]
    assert_log_error(lambda: read_frame_log(_log(mixed)), 4, "robot", "log is robot 'r1'")


def test_read_frame_log_holds_one_score_length() -> None:
    frames = _frames()
    seen = next(i for i, f in enumerate(frames) if f.detections)
    last = frames[-1]
    longer = tuple(dataclasses.replace(d, z_sem=np.append(d.z_sem, 0.5)) for d in last.detections)
    assert longer, "the paper's r1 sees an object at step 4"
    frames[-1] = dataclasses.replace(last, detections=longer)
    assert_log_error(
        lambda: read_frame_log(_log(frames)),
        5,
        "detections[0].z_sem",
        f"3 scores, but line {seen + 2} has 2",
    )


def test_read_frame_log_checks_the_header() -> None:
    one = format_frame_line(_frames()[0])
    assert_log_error(lambda: read_frame_log(['{"v":2,"type":"frame_log"}', one]), 1, "v", "2")
    assert_log_error(lambda: read_frame_log(['{"v":true}', one]), 1, "v", "version True")
    assert_log_error(lambda: read_frame_log(['{"v":1,"type":"x"}', one]), 1, "type", "'x'")
    extra = '{"v":1,"type":"frame_log","robot":"r1"}'
    assert_log_error(lambda: read_frame_log([extra, one]), 1, "header", "unknown keys")
    late = [one, format_header()]  # a header only opens a log
    assert_log_error(lambda: read_frame_log(late), 2, "header", "only the first line")


def test_read_frame_log_without_frames_is_an_error() -> None:
    for lines in ([], [format_header()], ["", " "]):
        assert_log_error(lambda lines=lines: read_frame_log(lines), 1, "frames", "no frame")


# --------------------------------------------------------------------------- fuzz

MUTATOR = fuzz.Mutator(
    known_keys=("robot", "k", "odometry", "detections", "id", "z_geo", "z_sem", "v", "type"),
    strings=("r1", "frame_log", "NaN", "", "x" * 33),
    edge_ints=(0, 1, -1, 2**32 - 1, 2**32, 2**63 - 1, 2**63, 10**400),
)
LINE_EDITS = st.lists(st.tuples(st.integers(0, 2**16), st.characters()), min_size=1, max_size=4)


def _to_json(doc: Any) -> str:
    """Any mutated document as a JSON line: bytes and other non-JSON values become their repr,
    keys JSON cannot hold are skipped, non-finite floats are written as NaN/Infinity."""
    return json.dumps(doc, default=repr, skipkeys=True)


def _parses_or_names_a_field(line: str, limits: FrameLimits | None = None) -> None:
    """Either a FrameLogError naming line 7 and a field, or a frame that formats back to itself."""
    try:
        frame = parse_frame_line(line, 7, limits)
    except FrameLogError as exc:
        assert exc.line == 7 and exc.field and str(exc).startswith(f"line 7: {exc.field}: ")
        return
    assert np.isnan(frame.true_pose).all()
    assert_same_frame(parse_frame_line(format_frame_line(frame, limits), 7, limits), frame)


@settings(FUZZ, max_examples=1000)
@given(data=st.data(), edits=st.integers(1, 3), base=st.integers(0, len(BASE_FRAMES) - 1))
def test_fuzz_mutated_lines_raise_only_frame_log_errors(
    data: st.DataObject, edits: int, base: int
) -> None:
    doc = json.loads(format_frame_line(BASE_FRAMES[base]))
    _parses_or_names_a_field(_to_json(MUTATOR.mutated(doc, edits, data)))


@settings(FUZZ, max_examples=1000)
@given(edits=LINE_EDITS, cut=st.integers(0, 2**16), base=st.integers(0, len(BASE_FRAMES) - 1))
def test_fuzz_corrupted_text_raises_only_frame_log_errors(
    edits: list[tuple[int, str]], cut: int, base: int
) -> None:
    line = list(format_frame_line(BASE_FRAMES[base]))
    for at, char in edits:
        line[at % len(line)] = char
    text = "".join(line)
    _parses_or_names_a_field(text)
    _parses_or_names_a_field(text[: cut % (len(text) + 1)], FrameLimits(num_classes=3))


JSON_NUMBERS = st.one_of(
    st.floats(),
    st.integers(-(2**70), 2**70),
    st.sampled_from((10**400, -(10**400), 2**1024, True, None, "1.0")),
)


NUMBER_FIELDS: tuple[fuzz.Path, ...] = (
    ("k",),
    ("odometry",),
    ("detections", 0, "id"),
    ("detections", 0, "z_geo"),
    ("detections", 1, "z_sem"),
)


@settings(FUZZ, max_examples=1000)
@given(
    path=st.sampled_from(NUMBER_FIELDS),
    value=JSON_NUMBERS | st.lists(JSON_NUMBERS, min_size=1, max_size=4),
    at=st.integers(0, 2),
)
def test_fuzz_numbers_raise_only_frame_log_errors(path: fuzz.Path, value: Any, at: int) -> None:
    """One number field of a valid line replaced, or one entry of its array."""
    doc = copy.deepcopy(REF_DOC)
    node = fuzz.get_at(doc, path)
    if isinstance(node, list) and not isinstance(value, list):
        node[at % len(node)] = value
    else:
        fuzz.set_at(doc, path, value)
    _parses_or_names_a_field(_to_json(doc))


@settings(FUZZ, max_examples=1000)
@given(text=st.text(max_size=200))
def test_fuzz_random_text_raises_only_frame_log_errors(text: str) -> None:
    _parses_or_names_a_field(text)


@settings(FUZZ, max_examples=1000)
@given(
    picks=st.lists(st.integers(0, 7), max_size=8),
    seed=st.integers(0, 2**32 - 1),
    data=st.data(),
)
def test_fuzz_logs_raise_only_frame_log_errors(picks: list[int], seed: int, data: Any) -> None:
    """Logs assembled from valid, mutated, blank and header lines in any order."""
    rng = np.random.default_rng(seed)
    k = [0]

    def line(pick: int) -> str:
        if pick == 0:
            return format_header()
        if pick == 1:
            return ""
        if pick == 2:
            return _to_json(MUTATOR.mutated(json.loads(REF_LINE), 1, data))
        k[0] += 1
        return format_frame_line(make_frame(rng, k=k[0] + (pick == 3), scores=2))

    lines = [line(p) for p in picks]
    try:
        frames = read_frame_log(lines)
    except FrameLogError as exc:
        assert 1 <= exc.line <= max(1, len(lines)) and exc.field, repr(exc)
        return
    assert [f.k for f in frames] == list(range(1, len(frames) + 1))
    assert len({f.robot for f in frames}) == 1
