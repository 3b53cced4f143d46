"""Helpers shared by command modules (argument types that give one-line errors)."""

from __future__ import annotations

import argparse
from pathlib import Path


def existing_file(text: str) -> Path:
    p = Path(text).expanduser()
    if not p.is_file():
        raise argparse.ArgumentTypeError(f"file not found: {text}")
    return p


def unit_interval(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}") from None
    if not 0.0 <= x <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {x:g}")
    return x


def positive_int(text: str) -> int:
    try:
        x = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive whole number, got {text!r}") from None
    if x <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive whole number, got {x}")
    return x


def positive_number(text: str) -> float:
    """A finite number greater than 0."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not (x > 0 and x != float("inf")):
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text!r}")
    return x


def non_negative_int(text: str) -> int:
    """A whole number 0 or more."""
    try:
        x = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number 0 or more, got {text!r}") from None
    if x < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number 0 or more, got {x}")
    return x


SEED_LIMIT = 2 ** 32
"""Seeds are whole numbers in [0, 2³²) (what numpy's and torch's generators take everywhere)."""


def seed(text: str) -> int:
    """A random seed: a whole number in [0, 2³²)."""
    try:
        x = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number 0 or more, got {text!r}") from None
    if not 0 <= x < SEED_LIMIT:
        raise argparse.ArgumentTypeError(f"expected a whole number in [0, 2^32), got {x}")
    return x


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
