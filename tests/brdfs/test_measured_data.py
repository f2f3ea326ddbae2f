"""Measured-material lookup (brdfs.measured_data): the real archives through $JAXRT_DATA in each of its
accepted layouts, checksums, and the messages for unknown names, missing and corrupt archives."""

from __future__ import annotations

import hashlib
import zipfile

import pytest

from brdfs import measured_data as md
from jaxrt.errors import InputError


def _clear_caches(monkeypatch):
    monkeypatch.setattr(md, "_verified", {})
    monkeypatch.setattr(md, "_listings", {})


@pytest.mark.data
def test_real_archives_names_and_checksums(brdf_data, monkeypatch):
    _clear_caches(monkeypatch)
    names = md.material_names()
    assert len(names) == 159 == len(set(names))
    counts = {c: sum(n.startswith(c + "/") for n in names) for c in md.ARCHIVES}
    assert counts == {"merl": 100, "rgl": 51, "nielsen": 8}
    assert {"merl/alum-bronze", "merl/gold-metallic-paint", "merl/chrome", "nielsen/bluebook"} <= set(names)
    for c, a in md.ARCHIVES.items():
        path = md.find_archive(c)
        assert hashlib.sha256(path.read_bytes()).hexdigest() == a.sha256
    m = md.find_material("merl/alum-bronze")
    assert m.member == "merl_nbrdf/alum-bronze.h5" and m.archive == brdf_data / "merl_nbrdf.zip"
    assert m.read_bytes()[:8] == b"\x89HDF\r\n\x1a\n"  # the HDF5 signature


@pytest.mark.data
def test_jaxrt_data_may_name_root_meshes_or_brdfs_folder(brdf_data, monkeypatch, tmp_path):
    root = brdf_data.parent
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "nocache"))
    for env in (root, root / "meshes", brdf_data):
        _clear_caches(monkeypatch)
        monkeypatch.setenv("JAXRT_DATA", str(env))
        assert md.find_material("nielsen/bluebook").archive == brdf_data / "nielsen_nbrdf.zip", env


@pytest.mark.data
def test_unknown_material_lists_close_matches(brdf_data):
    with pytest.raises(InputError, match=r"unknown measured material 'merl/alum-bronz'.*merl/alum-bronze"):
        md.find_material("merl/alum-bronz")
    with pytest.raises(InputError, match=r"unknown measured-material collection 'mer'.*merl, rgl, nielsen"):
        md.find_material("mer/alum-bronze")


def test_malformed_names():
    for bad in ("alum-bronze", "merl/a/b", 3):
        with pytest.raises(InputError, match="COLLECTION/NAME"):
            md.find_material(bad)


def _fake_archive(tmp_path, monkeypatch, members=("fake_nbrdf/a.h5", "fake_nbrdf/b.h5", "fake_nbrdf/b.json")):
    d = tmp_path / "data" / "brdfs"
    d.mkdir(parents=True)
    z = d / "fake.zip"
    with zipfile.ZipFile(z, "w") as zf:
        for n in members:
            zf.writestr(n, b"x")
    digest = hashlib.sha256(z.read_bytes()).hexdigest()
    monkeypatch.setitem(md.ARCHIVES, "fake", md.Archive("fake.zip", digest, "fake_nbrdf", 2))
    monkeypatch.setenv("JAXRT_DATA", str(tmp_path / "data" / "meshes"))  # meshes/ need not exist
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    _clear_caches(monkeypatch)
    return z


def test_lookup_in_fake_archive(tmp_path, monkeypatch):
    z = _fake_archive(tmp_path, monkeypatch)
    assert md.material_names("fake") == ("fake/a", "fake/b")
    m = md.find_material("fake/b")
    assert (m.archive, m.member, m.read_bytes()) == (z, "fake_nbrdf/b.h5", b"x")
    with pytest.raises(InputError, match=r"'fake/aa'; close matches: fake/a$"):
        md.find_material("fake/aa")
    with pytest.raises(InputError, match=r"'fake/zzz'; 2 materials, e.g. fake/a$"):
        md.find_material("fake/zzz")


def test_corrupt_archive_fails_checksum_in_one_line(tmp_path, monkeypatch):
    z = _fake_archive(tmp_path, monkeypatch)
    z.write_bytes(z.read_bytes() + b"tampered")
    _clear_caches(monkeypatch)
    with pytest.raises(InputError) as e:
        md.find_material("fake/a")
    msg = str(e.value)
    assert "\n" not in msg and str(z) in msg and hashlib.sha256(z.read_bytes()).hexdigest() in msg
    assert md.ARCHIVES["fake"].sha256 in msg and "asztr/Neural-BRDF" in msg


def test_wrong_member_count_is_refused(tmp_path, monkeypatch):
    _fake_archive(tmp_path, monkeypatch, members=("fake_nbrdf/a.h5",))
    with pytest.raises(InputError, match="expected 2 materials.*found 1"):
        md.material_names("fake")


def test_missing_archive_says_where_it_looked(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXRT_DATA", str(tmp_path))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    _clear_caches(monkeypatch)
    with pytest.raises(InputError) as e:
        md.find_material("merl/alum-bronze")
    msg = str(e.value)
    assert "merl_nbrdf.zip" in msg and str(tmp_path / "brdfs") in msg and "asztr/Neural-BRDF" in msg
    monkeypatch.delenv("JAXRT_DATA")
    with pytest.raises(InputError, match="JAXRT_DATA is not set"):
        md.find_material("merl/alum-bronze")
