"""Where UniPixie keeps caches and generated files.

Resolution order for the cache root:

1. ``UNIPIXIE_CACHE_DIR`` (environment),
2. a directory set programmatically with :func:`set_cache_root` (the Blender
   add-on does this from its preferences),
3. ``$XDG_CACHE_HOME/unipixie`` or ``~/.cache/unipixie``.

Nothing is ever written inside the source tree.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

_override: Path | None = None


def set_cache_root(path: str | os.PathLike | None) -> None:
    """Use ``path`` as the cache root for this process (``None`` restores the default)."""
    global _override
    _override = Path(path).expanduser().resolve() if path else None


def cache_root() -> Path:
    """The cache root directory (created on demand)."""
    env = os.environ.get("UNIPIXIE_CACHE_DIR")
    if env:
        root = Path(env).expanduser()
    elif _override is not None:
        root = _override
    else:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = Path(base) / "unipixie"
    root.mkdir(parents=True, exist_ok=True)
    return root


def cache_dir(kind: str) -> Path:
    """A sub-directory of the cache root for one kind of artefact (``"warp"``, ``"features"``, ...)."""
    if not kind or "/" in kind or "\\" in kind or kind.startswith("."):
        raise ValueError(f"cache kind must be a plain name, got {kind!r}")
    d = cache_root() / kind
    d.mkdir(parents=True, exist_ok=True)
    return d


def save_cached_array(path, array) -> Path:
    """Store ``array`` in the cache file ``path`` (``.npy``) atomically, through a unique temporary file: two
    processes filling the same cache entry never share a temporary, and a reader never sees half a file."""
    from .atomic_io import save_npy

    return save_npy(path, array)


def warp_kernel_cache_dir() -> Path:
    """Warp's kernel cache: ``UNIPIXIE_WARP_CACHE`` if set, else ``<cache root>/warp``."""
    env = os.environ.get("UNIPIXIE_WARP_CACHE")
    if env:
        p = Path(env).expanduser()
        p.mkdir(parents=True, exist_ok=True)
        return p
    return cache_dir("warp")


def content_key(*parts) -> str:
    """A stable hex digest of JSON-able parts and raw bytes, used to key cached results.

    ``bytes`` / ``bytearray`` / numpy arrays are hashed by content; everything
    else through ``json.dumps(sort_keys=True)``.
    """
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, (bytes, bytearray, memoryview)):
            h.update(b"b")
            h.update(bytes(part))
        elif hasattr(part, "tobytes") and hasattr(part, "dtype"):
            h.update(b"a")
            h.update(str(part.dtype).encode())
            h.update(str(getattr(part, "shape", "")).encode())
            h.update(part.tobytes())
        else:
            h.update(b"j")
            h.update(json.dumps(part, sort_keys=True, default=str).encode())
    return h.hexdigest()[:32]
