"""Helpers shared by command modules (argument types that give one-line errors)."""

from __future__ import annotations

import argparse
from pathlib import Path


def existing_file(text: str) -> Path:
    p = Path(text).expanduser()
    if not p.is_file():
        raise argparse.ArgumentTypeError(f"file not found: {text}")
    return p


def _number(text: str, cast, ok, expected: str, expected_value: str = "", show_text: bool = False):
    """``cast(text)`` if it parses and ``ok`` holds; else an ``ArgumentTypeError`` "expected …, got …"."""
    try:
        x = cast(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
    if not ok(x):
        shown = repr(text) if show_text else (f"{x:g}" if isinstance(x, float) else str(x))
        raise argparse.ArgumentTypeError(f"expected {expected_value or expected}, got {shown}")
    return x


def unit_interval(text: str) -> float:
    return _number(text, float, lambda x: 0.0 <= x <= 1.0, "a number in [0, 1]")


def positive_int(text: str) -> int:
    return _number(text, int, lambda x: x > 0, "a positive whole number")


def positive_number(text: str) -> float:
    """A finite number greater than 0."""
    return _number(text, float, lambda x: x > 0 and x != float("inf"), "a positive number",
                   "a positive finite number", show_text=True)


def non_negative_seconds(text: str) -> float:
    """A duration in seconds, 0 or more; ``inf`` for no limit."""
    return _number(text, float, lambda x: x >= 0.0, "a number of seconds, 0 or more (inf: no limit)", show_text=True)


def non_negative_int(text: str) -> int:
    """A whole number 0 or more."""
    return _number(text, int, lambda x: x >= 0, "a whole number 0 or more")


SEED_LIMIT = 2 ** 32
"""Seeds are whole numbers in [0, 2³²) (what numpy's and torch's generators take everywhere)."""


def seed(text: str) -> int:
    """A random seed: a whole number in [0, 2³²)."""
    return _number(text, int, lambda x: 0 <= x < SEED_LIMIT, "a whole number 0 or more",
                   "a whole number in [0, 2^32)")


def shard(text: str) -> tuple[int, int]:
    """``i/n`` with 0 <= i < n (0-based shard index)."""
    try:
        i, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a shard as i/n (e.g. 0/4), got {text!r}") from None
    if n <= 0 or not 0 <= i < n:
        raise argparse.ArgumentTypeError(f"shard {text!r}: need 0 <= i < n")
    return i, n


def device(text: str) -> str:
    t = text.strip().lower()
    if t not in ("cpu", "cuda", "auto") and not (t.startswith("cuda:") and t[5:].isdigit()):
        raise argparse.ArgumentTypeError(f"expected cpu, cuda, cuda:N or auto, got {text!r}")
    return t
