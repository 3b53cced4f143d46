"""training/baselines.py: how many dense training samples the baseline keeps on its device (no GPU needed)."""

import types

import pytest

torch = pytest.importorskip("torch")

from unipixie.training import baselines  # noqa: E402


def test_an_explicit_limit_is_kept_on_any_device():
    assert baselines.cache_has_room(3, 4, torch.device("cpu"))
    assert not baselines.cache_has_room(4, 4, torch.device("cpu"))
    assert not baselines.cache_has_room(4, 4, types.SimpleNamespace(type="cuda"))


def test_default_on_the_cpu_is_the_host_limit():
    assert baselines.cache_has_room(baselines.CPU_CACHE_LIMIT - 1, None, torch.device("cpu"))
    assert not baselines.cache_has_room(baselines.CPU_CACHE_LIMIT, None, torch.device("cpu"))


def test_default_on_a_gpu_follows_its_free_memory(monkeypatch):
    total = 80 * 2**30
    free = {"bytes": 60 * 2**30}
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (free["bytes"], total))
    gpu = types.SimpleNamespace(type="cuda")
    # far beyond the CPU's 1024 samples while the card has room (1,599 objects needed ~18 GB on an 80 GB H100)
    assert baselines.cache_has_room(5000, None, gpu)
    free["bytes"] = int(baselines.CACHE_FREE_FRACTION * total) - 1
    assert not baselines.cache_has_room(0, None, gpu)


def test_the_command_line_passes_the_limit(monkeypatch, tmp_path):
    seen = {}

    def fake_train(settings, log=print):
        seen["limit"] = settings.cache_limit
        return {"steps": 0, "device": "cpu", "seconds": 0.0, "samples_per_s": 0.0, "losses": [0.0]}

    monkeypatch.setattr(baselines, "train", fake_train)
    assert baselines.main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--cache-limit", "7"]) == 0
    assert seen["limit"] == 7
    assert baselines.main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 0
    assert seen["limit"] is None
