"""The data registry: lookup order, sha256 checks and the messages for missing/corrupt files."""

from __future__ import annotations

import hashlib

import pytest

from jaxrt.geometry import data
from jaxrt.errors import InputError


def test_registry_names_and_real_files(data_dir, monkeypatch):
    monkeypatch.setenv("JAXRT_DATA", str(data_dir))
    assert {"bunny", "dragon", "dragon_res2", "dragon_res4", "cornell_box"} <= set(data.names())
    for name in ("dragon_res4", "cornell_box"):
        p = data.find(name)
        assert p.parent in (data_dir, data_dir / "meshes")
        assert hashlib.sha256(p.read_bytes()).hexdigest() == data.REGISTRY[name].sha256


def _fake_entry(monkeypatch, content: bytes):
    monkeypatch.setitem(data.REGISTRY, "fake", data.Entry("fake.bin", hashlib.sha256(content).hexdigest(),
                                                          "https://example.org/fake.bin"))


def test_lookup_order_env_then_cache(tmp_path, monkeypatch):
    _fake_entry(monkeypatch, b"good")
    env, cache = tmp_path / "env", tmp_path / "xdg"
    (cache / "jaxrt").mkdir(parents=True)
    env.mkdir()
    (cache / "jaxrt" / "fake.bin").write_bytes(b"good")
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    monkeypatch.setenv("JAXRT_DATA", str(env))
    assert data.find("fake") == cache / "jaxrt" / "fake.bin"
    (env / "fake.bin").write_bytes(b"good")
    assert data.find("fake") == env / "fake.bin"


def test_jaxrt_data_may_name_the_data_root_holding_meshes(tmp_path, monkeypatch):
    # CI may point JAXRT_DATA at the shared data root (meshes/ beside the measured BRDFs' brdfs/) or
    # at the mesh folder itself: both find the meshes, the folder itself first
    _fake_entry(monkeypatch, b"good")
    root = tmp_path / "data"
    (root / "meshes").mkdir(parents=True)
    (root / "meshes" / "fake.bin").write_bytes(b"good")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    for env in (root, root / "meshes"):
        monkeypatch.setenv("JAXRT_DATA", str(env))
        assert data.find("fake") == root / "meshes" / "fake.bin"
    (root / "fake.bin").write_bytes(b"good")
    monkeypatch.setenv("JAXRT_DATA", str(root))
    assert data.find("fake") == root / "fake.bin"


def test_missing_file_says_where_to_get_it(tmp_path, monkeypatch):
    _fake_entry(monkeypatch, b"good")
    monkeypatch.setenv("JAXRT_DATA", str(tmp_path))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    with pytest.raises(InputError) as e:
        data.find("fake")
    msg = str(e.value)
    assert "fake.bin" in msg and str(tmp_path) in msg and "https://example.org/fake.bin" in msg and "JAXRT_DATA" in msg


def test_corrupt_file_fails_checksum(tmp_path, monkeypatch):
    _fake_entry(monkeypatch, b"good")
    monkeypatch.setenv("JAXRT_DATA", str(tmp_path))
    (tmp_path / "fake.bin").write_bytes(b"bad!")
    with pytest.raises(InputError) as e:
        data.find("fake")
    msg = str(e.value)
    assert "sha256" in msg and hashlib.sha256(b"bad!").hexdigest() in msg and "example.org" in msg


def test_unknown_name():
    with pytest.raises(InputError, match="unknown data name 'teapot'.*bunny"):
        data.find("teapot")
