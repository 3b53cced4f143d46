"""The fault matrix's verdict checks: what an exit 0 claims, checked against the crafted input
(``Case.check``: called with the case folder and the (stdout, stderr) texts; None, or what is false)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np


# --------------------------------------------------------------------------- verdict checks
def verdict_not_explained(d: Path, texts) -> Optional[str]:
    v = json.loads((d / "rep" / "diagnosis.json").read_text())["verdict"]
    if v.get("explained") or v.get("code") == "explained":
        return f"diagnosis says '{v.get('sentence')}' for a measurement far from the model"
    return None


def verdict_explained_or_refused(d: Path, texts) -> Optional[str]:
    return None


def csv_same_as_npz(d: Path, texts) -> Optional[str]:
    with np.load(d / "out.npz") as a, np.load(d / "m.npz") as b:
        if a["positions"].shape != b["positions"].shape:
            return f"positions {a['positions'].shape} vs {b['positions'].shape}"
        if not np.allclose(a["positions"], b["positions"], equal_nan=True, atol=1e-12):
            return "the reordered CSV gives other positions than the original"
    return None


def says(needle: str):
    def check(d: Path, texts) -> Optional[str]:
        if not any(needle in (o + e) for o, e in texts):
            return f"exit 0 without saying {needle!r}"
        return None
    return check


def output_exists(rel: str):
    def check(d: Path, texts):
        return None if (d / rel).exists() else f"exit 0 but {rel} was not written"
    return check
