"""The bake record: the JSON stored on a baked object (ID property :data:`BAKE_RECORD_KEY`, format
``unipixie.bake/1``) listing everything the bake added, so that clearing it removes exactly that
(:func:`make_record`, :func:`parse_record`, :func:`effects_to_json`).

Uses json and :func:`unipixie.core.atomic_io.json_default`.
"""

from __future__ import annotations

import json
from typing import Iterable, Optional

from ..atomic_io import json_default


BAKE_RECORD_KEY = "unipixie_bake"
"""ID property on a baked object holding the JSON record of everything the bake added."""
BAKE_RECORD_FORMAT = "unipixie.bake/1"


def make_record(**fields) -> str:
    """The JSON stored on a baked object (:data:`BAKE_RECORD_KEY`): what was made, so clear_bake can undo it."""
    doc = {"format": BAKE_RECORD_FORMAT}
    doc.update(fields)
    return json.dumps(doc, default=json_default)


def parse_record(text) -> Optional[dict]:
    if not text:
        return None
    try:
        doc = json.loads(str(text))
    except json.JSONDecodeError:
        return None
    if not isinstance(doc, dict) or doc.get("format") != BAKE_RECORD_FORMAT:
        return None
    return doc


def effects_to_json(effects: Iterable) -> list:
    return [e.to_dict() if hasattr(e, "to_dict") else e for e in effects]
