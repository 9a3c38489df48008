"""Argument types shared by the ``semfleet`` commands: one clear sentence for a bad value."""

from __future__ import annotations

import argparse

from sim.loader import MAX_CLASSES

MAX_SEED = 2**63 - 1


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None


def positive_int(text: str) -> int:
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} must be a positive integer")
    return value


def class_count(text: str) -> int:
    value = _integer(text)
    if not 2 <= value <= MAX_CLASSES:
        raise argparse.ArgumentTypeError(f"{text}: need 2 to {MAX_CLASSES} classes")
    return value


def seed(text: str) -> int:
    value = _integer(text)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"{text}: seeds are non-negative integers below 2**63")
    return value
