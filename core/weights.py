"""Fetching the OpenCLIP weights a model's features need (``unipixie weights fetch``, the add-on's *Fetch CLIP
weights*), for users who are online.

Which weights: a CLIP feature model (the name a checkpoint's feature recipe or config gives, e.g. ``ViT-B-16``)
→ the OpenCLIP pretrained tag :data:`~unipixie.core.clip_features.OPENCLIP_PRETRAINED` names for it → the
Hugging Face Hub repository open_clip's own pretrained registry gives for that pair
(``open_clip.get_pretrained_cfg(architecture, tag)["hf_hub"]``).  From the repository: ``open_clip_config.json``
(when the repository has one) and the weights, ``open_clip_model.safetensors`` or else
``open_clip_pytorch_model.bin`` (open_clip's own order).

Where: the default weights folder :func:`~unipixie.core.clip_features.default_weights_dir`
(``<cache>/clip/<architecture>/``), which feature extraction finds without any setting.

How: ``huggingface_hub.hf_hub_download(..., local_dir=folder)`` — the hub library's own download: its progress
bar, its retries that resume a dropped connection with an HTTP ``Range`` request, its size check, its temporary
file renamed into place only when complete (an interrupted download never leaves a partial file under the final
name), its settings (``HF_ENDPOINT`` for a mirror, ``HF_HUB_OFFLINE``, ``HF_TOKEN``).  A file already there with
the Hub's checksum is not downloaded again.  Before downloading, the file's metadata is asked for once (fails at
once with a clear message when offline); after it, the file's SHA-256 is compared with the checksum the Hub
announces (the ETag of a large-file-storage file is its SHA-256; a small file's is its git blob hash).  A
mismatch removes the file and is an error.
"""

from __future__ import annotations

import hashlib
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from .errors import CancelledError, UserError

CONFIG_FILE = "open_clip_config.json"
"""The config file of an open_clip Hub repository (``open_clip.constants.HF_CONFIG_NAME``)."""


@dataclass(frozen=True)
class WeightsSource:
    """Where the weights of a CLIP feature model come from.

    feature_model: the name feature grids and checkpoints record (the OpenCLIP architecture, e.g. ``ViT-B-16``).
    pretrained: open_clip's pretrained tag.  repo_id: the Hub repository.  weight_files: candidate weight files in
    the order they are tried.  endpoint: the Hub endpoint used (``HF_ENDPOINT`` or the default).
    """

    feature_model: str
    pretrained: str
    repo_id: str
    weight_files: tuple
    endpoint: str


@dataclass
class FetchResult:
    """What a fetch did.  files: the files now in ``folder`` (config, weights) with their verified SHA-256;
    downloaded: the names actually transferred (others were there already); notes: warnings."""

    source: WeightsSource
    folder: Path
    files: dict = field(default_factory=dict)
    downloaded: list = field(default_factory=list)
    seconds: float = 0.0
    notes: list = field(default_factory=list)

    def summary(self) -> str:
        weights = next((n for n in self.files if n != CONFIG_FILE), "?")
        got = (f"downloaded {', '.join(self.downloaded)}" if self.downloaded else "already present")
        return (f"{self.source.feature_model} {self.source.pretrained} weights in {self.folder} ({weights}, "
                f"SHA-256 {self.files.get(weights, '')[:12]}… verified; {got}; {self.seconds:.1f} s)")


def weights_source(feature_model: str = "") -> WeightsSource:
    """The Hub repository and files of ``feature_model``'s OpenCLIP weights (default: the paper's ViT-B-16)."""
    from . import clip_features as cf

    feature_model = feature_model or cf.CLIP_MODEL
    if feature_model == cf.OFFLINE_FEATURE_MODEL or feature_model.startswith(cf.OFFLINE_FEATURE_MODEL):
        raise UserError(f"'{feature_model}' is the offline extractor (a seeded, untrained ViT): it needs no weights")
    from .extractors import description, needs_weights

    if not needs_weights(feature_model):
        raise UserError(f"'{feature_model}' is the {description(feature_model)}: it needs no weights")
    tag = cf.OPENCLIP_PRETRAINED.get(feature_model)
    if tag is None:
        raise UserError(f"no OpenCLIP weights are known for the feature model '{feature_model}' (known: "
                        f"{', '.join(f'{m} ({t})' for m, t in cf.OPENCLIP_PRETRAINED.items())}); put its weights in "
                        f"{cf.default_weights_dir(feature_model)} or set 'CLIP weights' / --clip-weights")
    import open_clip
    from huggingface_hub import constants
    from open_clip.constants import HF_SAFE_WEIGHTS_NAME, HF_WEIGHTS_NAME

    hub = (open_clip.get_pretrained_cfg(feature_model, tag) or {}).get("hf_hub", "")
    if not hub:
        raise UserError(f"open_clip {open_clip.__version__} lists no Hugging Face Hub repository for {feature_model} "
                        f"{tag}; download its weights by hand into {cf.default_weights_dir(feature_model)}")
    repo_id, filename = os.path.split(hub)           # open_clip's convention: 'org/repo/' or 'org/repo/file.bin'
    files = (filename,) if filename else (HF_SAFE_WEIGHTS_NAME, HF_WEIGHTS_NAME)
    return WeightsSource(feature_model, tag, repo_id, files, constants.ENDPOINT)


class _JobProgressBar:
    """The hub library's progress-bar interface (its ``tqdm_class``) forwarding the bytes of one file to a
    :class:`~unipixie.core.progress.Progress` whose total is the file's size (the add-on's progress bar; Esc
    cancels the download: the step raises in the downloading thread)."""

    def __init__(self, progress, name: str, **_):
        self.progress, self.name, self.n = progress, name, 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def update(self, n=1):
        self.n += int(n)
        self.progress.step(int(n), f"{self.n / 1e6:.1f} of {self.progress.total / 1e6:.1f} MB")

    def close(self):
        pass


def _bar_class(progress, name: str):
    if progress is None:
        return None                         # the hub library's own tqdm bar on stderr

    def make(**kwargs):
        return _JobProgressBar(progress, name, **kwargs)

    return make


def _digest(path: Path, h) -> str:
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 22), b""):
            h.update(chunk)
    return h.hexdigest()


def sha256_of(path: Path) -> str:
    return _digest(path, hashlib.sha256())


def file_checksum(path: Path, etag: str) -> tuple[str, str]:
    """(the file's checksum of the ETag's kind, the kind): SHA-256 for a 64-hex ETag (large-file storage), the git
    blob hash (SHA-1 of ``blob <size>\\0`` + content) for a 40-hex ETag (a small file kept in git)."""
    if len(etag) == 64:
        return sha256_of(path), "SHA-256"
    return _digest(path, hashlib.sha1(f"blob {path.stat().st_size}\0".encode())), "git blob SHA-1"


def _offline_error(source: WeightsSource, exc: Exception) -> UserError:
    from huggingface_hub import constants

    if constants.HF_HUB_OFFLINE:
        why = "HF_HUB_OFFLINE is set, so the Hugging Face Hub library makes no network requests"
    else:
        why = f"cannot reach {source.endpoint} ({type(exc).__name__}: {str(exc).splitlines()[0][:160]})"
    return UserError(f"could not fetch the {source.feature_model} {source.pretrained} CLIP weights: {why}. Connect to "
                     f"the internet (or set HF_ENDPOINT to a reachable mirror) and run 'unipixie weights fetch' again, "
                     f"or copy the weights by hand into the folder 'unipixie weights status' names")


def _metadata(source: WeightsSource, filename: str, endpoint: Optional[str]):
    """The Hub's metadata of one file (one HEAD request, no retries), or ``None`` when the repository lacks it."""
    import httpx2
    from huggingface_hub import get_hf_file_metadata, hf_hub_url
    from huggingface_hub.errors import (GatedRepoError, HfHubHTTPError, OfflineModeIsEnabled, RemoteEntryNotFoundError,
                                        RepositoryNotFoundError)

    try:
        return get_hf_file_metadata(hf_hub_url(source.repo_id, filename, endpoint=endpoint), endpoint=endpoint)
    except RemoteEntryNotFoundError:
        return None
    except GatedRepoError as exc:
        raise UserError(f"{source.repo_id} on {source.endpoint} is gated: accept its terms on the website and log in "
                        f"('hf auth login') first ({str(exc).splitlines()[0]})") from None
    except RepositoryNotFoundError:
        raise UserError(f"{source.endpoint} has no repository {source.repo_id} (the {source.feature_model} "
                        f"{source.pretrained} weights); check HF_ENDPOINT") from None
    except (OfflineModeIsEnabled, httpx2.TransportError) as exc:
        raise _offline_error(source, exc) from None
    except HfHubHTTPError as exc:
        raise UserError(f"{source.endpoint} refused {source.repo_id}/{filename}: {str(exc).splitlines()[0]}") from None


def _download(source: WeightsSource, filename: str, folder: Path, endpoint: Optional[str], progress, force: bool):
    """``hf_hub_download`` of one file into ``folder``; returns (path, transferred?)."""
    import httpx2
    from huggingface_hub import hf_hub_download
    from huggingface_hub.errors import HfHubHTTPError, LocalEntryNotFoundError, OfflineModeIsEnabled

    before = _stamp(folder / filename)
    try:
        path = hf_hub_download(source.repo_id, filename, local_dir=folder, endpoint=endpoint, force_download=force,
                               tqdm_class=_bar_class(progress, filename), library_name="unipixie")
    except CancelledError:
        raise
    except (LocalEntryNotFoundError, OfflineModeIsEnabled, httpx2.TransportError) as exc:
        raise _offline_error(source, exc) from None
    except HfHubHTTPError as exc:
        raise UserError(f"downloading {source.repo_id}/{filename} from {source.endpoint} failed: "
                        f"{str(exc).splitlines()[0]}") from None
    except OSError as exc:            # the hub's size check ("Consistency check failed"), a full disk, ...
        raise UserError(f"downloading {source.repo_id}/{filename} from {source.endpoint} failed: "
                        f"{str(exc).splitlines()[0]}; nothing was kept, run the command again") from None
    return Path(path), _stamp(Path(path)) != before


def _stamp(path: Path):
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns, st.st_ino


def fetch_weights(feature_model: str = "", folder=None, endpoint: Optional[str] = None, progress=None,
                  force: bool = False) -> FetchResult:
    """Download ``feature_model``'s OpenCLIP weights (default ViT-B-16 laion2b_s34b_b88k) into ``folder`` (default:
    :func:`~unipixie.core.clip_features.default_weights_dir`, where feature extraction looks) and verify them.

    endpoint: the Hub endpoint (default: ``$HF_ENDPOINT`` as it is now, else https://huggingface.co).  progress: a
    :class:`~unipixie.core.progress.Progress` for the transferred bytes (cancelling it stops the download and
    keeps nothing of the file); ``None`` shows the hub library's own progress bar.  force: download even when a
    verified copy is there.  Raises :class:`UserError` when offline, when the Hub lacks the files, and when a
    downloaded file's checksum differs from the Hub's (the file is removed).
    """
    from . import clip_features as cf

    t0 = time.perf_counter()
    source = weights_source(feature_model)
    endpoint = endpoint or os.environ.get("HF_ENDPOINT") or None      # read now (the hub library reads it at import)
    if endpoint:
        source = WeightsSource(source.feature_model, source.pretrained, source.repo_id, source.weight_files,
                               endpoint.rstrip("/"))
    folder = Path(folder) if folder else cf.default_weights_dir(source.feature_model)
    folder.mkdir(parents=True, exist_ok=True)
    result = FetchResult(source, folder)
    wanted = []
    config = _metadata(source, CONFIG_FILE, endpoint)
    if config is not None:
        wanted.append((CONFIG_FILE, config))
    for name in source.weight_files:
        meta = _metadata(source, name, endpoint)
        if meta is not None:
            wanted.append((name, meta))
            break
    else:
        raise UserError(f"{source.endpoint}/{source.repo_id} has none of the weight files "
                        f"{', '.join(source.weight_files)}")
    sizes = [max(1, int(meta.size or 1)) for _, meta in wanted]
    for (name, meta), size in zip(wanted, sizes):
        etag = (meta.etag or "").strip('"').lower()
        bar = progress.sub(progress.total * size / sum(sizes), size, name) if progress is not None else None
        path, transferred = _download(source, name, folder, endpoint, bar, force)
        if transferred:
            result.downloaded.append(name)
        if len(etag) not in (40, 64) or any(c not in "0123456789abcdef" for c in etag):
            actual = sha256_of(path)
            result.notes.append(f"{source.endpoint} announced no checksum for {name} (ETag {meta.etag!r}); its "
                                f"SHA-256 is {actual}")
            result.files[name] = actual
            continue
        actual, kind = file_checksum(path, etag)
        if actual != etag:
            path.unlink(missing_ok=True)
            raise UserError(f"checksum mismatch for {source.repo_id}/{name} from {source.endpoint}: the Hub announces "
                            f"{kind} {etag}, the downloaded file has {actual}; the file was removed (a broken "
                            "mirror, proxy or disk); run 'unipixie weights fetch' again")
        result.files[name] = actual if kind == "SHA-256" else sha256_of(path)
    result.seconds = time.perf_counter() - t0
    return result


def fetch_job(feature_model: str = "", folder=None, force: bool = False):
    """:func:`fetch_weights` as a job generator of ``(fraction, status)`` (the download runs in a worker thread;
    closing the generator — Esc in Blender — cancels it and keeps nothing of the file being downloaded).
    Returns the :class:`FetchResult`."""
    from .jobs import worker_job

    source = weights_source(feature_model)
    yield 0.0, f"asking {source.endpoint} for {source.feature_model} {source.pretrained}"
    result = yield from worker_job(lambda progress: fetch_weights(source.feature_model, folder, progress=progress,
                                                                  force=force),
                                   description="fetch CLIP weights", idle_status="downloading", name="unipixie-fetch")
    yield 1.0, "verified"
    return result
