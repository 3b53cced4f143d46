"""`unipixie weights fetch` end to end against a stand-in for the Hugging Face Hub on 127.0.0.1.

The stand-in serves a small seeded OpenCLIP checkpoint (a 3-layer ViT of width 320, 14 MB: more than the hub
library's 10 MB download chunk, so an interruption can happen after a chunk was saved) in the Hub's layout
(``/<repo>/resolve/<revision>/<file>``, with the ``X-Repo-Commit`` and ``ETag`` headers the Hub sends, ``Range``
requests answered with 206) under the repository open_clip's registry names for ViT-B-16 laion2b_s34b_b88k.
The command reaches it through ``HF_ENDPOINT``, the hub library's own endpoint setting.  Nothing here reaches the
internet: every URL is http://127.0.0.1.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from unipixie.core import clip_features as cf
from unipixie.core import weights
from unipixie.core.errors import CancelledError, UserError
from unipixie.core.progress import Progress

COMMIT = "0123456789abcdef0123456789abcdef01234567"
WIDTH = 320
TINY_CFG = {"embed_dim": 32,
            "vision_cfg": {"image_size": 64, "patch_size": 16, "width": WIDTH, "layers": 3, "head_width": 64},
            "text_cfg": {"context_length": 8, "vocab_size": 64, "width": 8, "heads": 1, "layers": 1}}


def _git_blob_sha1(data: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"

    def log_message(self, *args):       # quiet
        pass

    def do_HEAD(self):
        self._serve(body=False)

    def do_GET(self):
        self._serve(body=True)

    def _serve(self, body: bool):
        hub = self.server.hub
        hub.log.append((self.command, self.path, self.headers.get("Range")))
        parts = self.path.split("?")[0].strip("/").split("/")
        if len(parts) < 5 or parts[2] != "resolve":
            return self._reply(404, b"", {"X-Error-Code": "RepoNotFound"})
        repo, name = "/".join(parts[:2]), "/".join(parts[4:])
        if repo != hub.repo:
            return self._reply(404, b"", {"X-Error-Code": "RepoNotFound"})
        data = hub.files.get(name)
        if data is None:
            return self._reply(404, b"", {"X-Error-Code": "EntryNotFound", "X-Repo-Commit": COMMIT})
        lfs = not name.endswith(".json")
        etag = hashlib.sha256(data).hexdigest() if lfs else _git_blob_sha1(data)
        if name in hub.wrong_checksum:
            etag = hashlib.sha256(b"not the served bytes").hexdigest()
        headers = {"X-Repo-Commit": COMMIT, "ETag": f'"{etag}"', "Accept-Ranges": "bytes"}
        start = 0
        rng = self.headers.get("Range")
        if rng and rng.startswith("bytes=") and body:
            start = int(rng[6:].split("-")[0])
            headers["Content-Range"] = f"bytes {start}-{len(data) - 1}/{len(data)}"
        status = 206 if start else 200
        if not body:
            return self._reply(200, b"", headers, length=len(data))
        cut = hub.interrupt.pop(name, None)
        if cut is not None and not start:              # send part of the file, then drop the connection
            self.send_response(200)
            for k, v in {**headers, "Content-Length": str(len(data))}.items():
                self.send_header(k, v)
            self.end_headers()
            self.wfile.write(data[:cut])
            self.wfile.flush()
            hub.served.append((name, 0, cut))
            self.connection.shutdown(socket.SHUT_RDWR)
            self.close_connection = True
            return
        hub.served.append((name, start, len(data)))
        self._reply(status, data[start:], headers)

    def _reply(self, status, payload: bytes, headers: dict, length=None):
        self.send_response(status)
        for k, v in headers.items():
            self.send_header(k, v)
        self.send_header("Content-Length", str(len(payload) if length is None else length))
        self.end_headers()
        if self.command == "GET" and payload:
            self.wfile.write(payload)


class HubStandIn:
    """The loopback Hub: ``files`` served for ``repo``; ``interrupt[name] = n`` drops the first GET of ``name``
    after n bytes; names in ``wrong_checksum`` are announced with another SHA-256; ``log`` / ``served`` record
    the requests and the byte ranges sent."""

    def __init__(self, repo: str, files: dict):
        self.repo, self.files = repo, files
        self.interrupt: dict = {}
        self.wrong_checksum: set = set()
        self.log: list = []
        self.served: list = []
        self.server = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
        self.server.hub = self
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self._thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self._thread.start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture(scope="module")
def checkpoint_files():
    """A small seeded OpenCLIP checkpoint in the layout of an open_clip Hub repository."""
    import open_clip
    import torch
    from safetensors.torch import save

    torch.manual_seed(7)
    model = open_clip.create_model("ViT-B-16", pretrained=None, **TINY_CFG)
    state = {k: v.detach().contiguous() for k, v in model.state_dict().items()}
    return {"open_clip_config.json": json.dumps({"model_cfg": TINY_CFG, "preprocess_cfg": {}}).encode(),
            "open_clip_model.safetensors": save(state)}


@pytest.fixture
def hub(checkpoint_files):
    src = weights.weights_source("ViT-B-16")
    server = HubStandIn(src.repo_id, dict(checkpoint_files))
    yield server
    server.close()


def _env(tmp_path, hub, **extra):
    env = {**os.environ, "HF_ENDPOINT": hub.url, "UNIPIXIE_CACHE_DIR": str(tmp_path / "cache"),
           "HF_HOME": str(tmp_path / "hf"), "HF_HUB_DISABLE_TELEMETRY": "1", "NO_PROXY": "127.0.0.1,localhost",
           "no_proxy": "127.0.0.1,localhost"}
    env.pop(cf.CLIP_WEIGHTS_ENV, None)
    env.update(extra)
    return env


def _fetch(env, *args):
    return subprocess.run([sys.executable, "-m", "unipixie.cli", "weights", "fetch", *args], capture_output=True,
                          text=True, env=env, timeout=300)


def test_fetch_resumes_an_interrupted_download_verifies_it_and_extraction_uses_it(hub, tmp_path, monkeypatch):
    weights_name = "open_clip_model.safetensors"
    size = len(hub.files[weights_name])
    assert size > 12_000_000
    hub.interrupt[weights_name] = 12_000_000          # the connection drops after 12 MB of the first GET
    res = _fetch(_env(tmp_path, hub))
    assert res.returncode == 0, res.stderr[-3000:]
    assert "downloaded open_clip_config.json, open_clip_model.safetensors" in res.stdout
    assert "verified" in res.stdout and hub.repo in res.stdout

    gets = [(path, rng) for method, path, rng in hub.log if method == "GET" and path.endswith(weights_name)]
    assert len(gets) == 2 and gets[0][1] is None
    resumed_at = int(gets[1][1].split("=")[1].rstrip("-"))       # the second GET asks only for the rest
    assert 0 < resumed_at <= 12_000_000
    assert (weights_name, resumed_at, size) in hub.served

    folder = tmp_path / "cache" / "clip" / "ViT-B-16"
    for name, data in hub.files.items():
        assert (folder / name).read_bytes() == data
    assert not [p for p in folder.rglob("*") if p.name.endswith(".incomplete")]

    # feature extraction finds the weights in the default folder, without any setting
    monkeypatch.setenv("UNIPIXIE_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv(cf.CLIP_WEIGHTS_ENV, raising=False)
    assert cf.resolve_clip_weights() == folder
    extractor = cf.make_extractor()
    feats = extractor(np.random.default_rng(0).random((2, 64, 64, 3), dtype=np.float32))
    assert extractor.is_clip and tuple(feats.shape) == (2, 4, 4, WIDTH)

    # a second fetch finds the verified copy: no GET, nothing transferred
    n = len(hub.log)
    res = _fetch(_env(tmp_path, hub))
    assert res.returncode == 0 and "already present" in res.stdout, res.stderr[-2000:]
    assert not [m for m, _, _ in hub.log[n:] if m == "GET"]


def test_a_wrong_checksum_is_refused_and_the_file_not_kept(hub, tmp_path):
    hub.wrong_checksum.add("open_clip_model.safetensors")
    res = _fetch(_env(tmp_path, hub))
    assert res.returncode == 2, res.stderr[-2000:]
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("unipixie weights: error: checksum mismatch for")
    assert "SHA-256" in err[0] and hashlib.sha256(hub.files["open_clip_model.safetensors"]).hexdigest() in err[0]
    folder = tmp_path / "cache" / "clip" / "ViT-B-16"
    assert not (folder / "open_clip_model.safetensors").exists()
    assert not [p for p in folder.rglob("*") if p.name.endswith(".incomplete")]
    # the next fetch from a good server downloads it again
    hub.wrong_checksum.clear()
    res = _fetch(_env(tmp_path, hub))
    assert res.returncode == 0 and (folder / "open_clip_model.safetensors").is_file(), res.stderr[-2000:]


def test_offline_is_said_clearly_and_quickly(tmp_path, monkeypatch, hub):
    closed = socket.socket()
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    closed.close()                                   # nothing listens there: connection refused
    t0 = time.perf_counter()
    with pytest.raises(UserError, match=r"cannot reach http://127\.0\.0\.1:\d+ .*Connect to the internet"):
        weights.fetch_weights("ViT-B-16", folder=tmp_path / "w", endpoint=f"http://127.0.0.1:{port}")
    assert time.perf_counter() - t0 < 10.0
    res = _fetch(_env(tmp_path, hub, HF_HUB_OFFLINE="1"))
    assert res.returncode == 2 and "HF_HUB_OFFLINE is set" in res.stderr and "Traceback" not in res.stderr
    assert not [m for m, _, _ in hub.log]          # offline mode sent nothing


def test_progress_reaches_the_end_and_cancelling_keeps_nothing(hub, tmp_path):
    seen = []
    progress = Progress(callback=lambda fraction, status: seen.append((fraction, status)), show_bar=False)
    result = weights.fetch_weights("ViT-B-16", folder=tmp_path / "a", endpoint=hub.url, progress=progress)
    assert result.downloaded == ["open_clip_config.json", "open_clip_model.safetensors"]
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == pytest.approx(1.0)
    assert any(0.5 < f < 0.99 for f in fractions)                  # the bar follows the bytes of both files
    assert seen[-1][1].startswith("open_clip_model.safetensors: ") and seen[-1][1].endswith(" MB")
    assert result.files["open_clip_model.safetensors"] == hashlib.sha256(
        hub.files["open_clip_model.safetensors"]).hexdigest()

    cancelling = Progress(callback=lambda fraction, status: cancelling.cancel(), show_bar=False)
    with pytest.raises(CancelledError):
        weights.fetch_weights("ViT-B-16", folder=tmp_path / "b", endpoint=hub.url, progress=cancelling)
    assert not (tmp_path / "b" / "open_clip_model.safetensors").exists()
    assert not [p for p in (tmp_path / "b").rglob("*") if p.name.endswith(".incomplete")]


def test_the_offline_extractor_needs_no_weights_and_unknown_models_are_named():
    with pytest.raises(UserError, match="needs no weights"):
        weights.weights_source(cf.OFFLINE_FEATURE_MODEL)
    with pytest.raises(UserError, match="no OpenCLIP weights are known for the feature model 'ViT-X'"):
        weights.weights_source("ViT-X")


def test_the_panel_button_fetches_and_the_features_options_say_what_the_model_expects(blender, hub, tmp_path,
                                                                                      monkeypatch):
    """The add-on: the Features sub-panel's line names the extractor the model expects; with a model trained on
    ViT-B-16 features and no weights it offers *Fetch CLIP weights*, which downloads them (job operator)."""
    import shutil

    bpy = blender
    from unipixie.core.model import UniPixieModel, preset, save_model
    from unipixie.unipixie_addon import preferences

    monkeypatch.setenv("HF_ENDPOINT", hub.url)
    monkeypatch.setenv("UNIPIXIE_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv(cf.CLIP_WEIGHTS_ENV, raising=False)
    wm = bpy.context.window_manager
    preferences.store_extractor_info(bpy.context)
    assert "expects appearance-gbuffer-v1 features" in wm.unipixie_extractor_info and not wm.unipixie_extractor_fetch

    clip_model = save_model(UniPixieModel(preset("tiny", feature_model="ViT-B-16", feature_dim=WIDTH, patch_size=4,
                                                 spring_anchors=8)), tmp_path / "clip_model")
    monkeypatch.setattr(preferences._Defaults, "checkpoint", str(clip_model))
    preferences.store_extractor_info(bpy.context)
    assert "expects ViT-B-16 CLIP features" in wm.unipixie_extractor_info and "missing" in wm.unipixie_extractor_info
    assert wm.unipixie_extractor_fetch == "ViT-B-16"

    assert bpy.ops.unipixie.fetch_clip_weights(model=wm.unipixie_extractor_fetch) == {"FINISHED"}
    folder = tmp_path / "cache" / "clip" / "ViT-B-16"
    assert (folder / "open_clip_model.safetensors").read_bytes() == hub.files["open_clip_model.safetensors"]
    assert f"weights: {folder}" in wm.unipixie_extractor_info and not wm.unipixie_extractor_fetch
    # the pipeline now extracts the model's features from those weights
    from unipixie.core.pipeline import PipelineSettings

    options = PipelineSettings(checkpoint=str(clip_model)).feature_options()
    assert not options.offline and options.clip_model == "ViT-B-16"
    shutil.rmtree(folder)
