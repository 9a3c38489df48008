"""The shared checks of the codecs keep their verdicts on their fast paths, and the cache of robot
ids found valid stays bounded whatever ids arrive."""

from __future__ import annotations

import pytest

from protocol import validate
from protocol.errors import InvalidValue, MalformedMessage
from protocol.validate import as_int, as_map, robot_id, valid_id


def test_valid_ids_are_remembered_invalid_ones_never_and_the_memory_is_bounded() -> None:
    validate._VALID_IDS.clear()
    assert valid_id("r1") and "r1" in validate._VALID_IDS
    for bad in ("", "r 1", "x" * 33, "r/1", 7, None, b"r1"):
        assert not valid_id(bad)
    assert {"r1"} == validate._VALID_IDS
    for i in range(3 * validate._MAX_VALID_IDS):  # a flood of made-up ids
        assert valid_id(f"id{i}")
        assert len(validate._VALID_IDS) <= validate._MAX_VALID_IDS
    assert valid_id("r1") and not valid_id("r 1")


class Id(str):
    """A str subclass: valid by its text, returned as a plain str."""


class Count(int):
    pass


def test_the_checks_give_the_same_verdicts_on_and_off_their_fast_paths() -> None:
    assert robot_id("r1", "f") == "r1" and type(robot_id(Id("r2"), "f")) is str
    with pytest.raises(InvalidValue, match=r"^f: invalid robot id"):
        robot_id("r 1", "f")
    with pytest.raises(MalformedMessage, match=r"^f: expected a string"):
        robot_id(b"r1", "f")
    assert as_int(5, "f", 0, 9) == 5 and type(as_int(Count(5), "f", 0, 9)) is int
    for bad, error in ((True, MalformedMessage), (5.0, MalformedMessage), (10, InvalidValue)):
        with pytest.raises(error):
            as_int(bad, "f", 0, 9)
    keys = frozenset({"a", "b"})
    assert as_map({"a": 1, "b": 2}, "f", keys) == {"a": 1, "b": 2}
    with pytest.raises(MalformedMessage, match="missing keys"):
        as_map({"a": 1}, "f", keys)
    with pytest.raises(MalformedMessage, match="unknown keys"):
        as_map({"a": 1, "b": 2, "c": 3}, "f", keys)
