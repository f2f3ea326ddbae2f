"""Every shipped scene renders finite pixels; `jaxrt render` end to end (files, exit codes, errors)."""

from __future__ import annotations

import numpy as np
import pytest

from jaxrt import cli, image
import jaxrt as R
from jaxrt import scene as S

SMALL = {"camera.width": 24, "camera.height": 24}


def _check_finite(name):
    img, aovs = R.frame(S.load(name, overrides=SMALL), aovs=True)
    img = np.asarray(img)
    assert img.shape == (24, 24, 3) and np.all(np.isfinite(img)), f"{name}: non-finite pixels"
    assert img.max() > 0.0, f"{name}: black image"
    for k, v in aovs.items():
        assert np.all(np.isfinite(np.asarray(v))), f"{name}: non-finite {k}"
    assert np.any(np.asarray(aovs["object_id"]) >= 0)


def test_cli_writes_exr_and_png_atomically_and_exr_round_trips(tmp_path, capsys):
    exr, png = tmp_path / "s.exr", tmp_path / "s.png"
    rc = cli.main(["render", "spheres", "-o", str(exr), "--png", str(png), "--width", "24", "--height", "24",
                   "--aovs", "--exposure", "0.5"])
    assert rc == 0, capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.exr", "s.png"]  # no temporaries left
    ch = image.read_exr(exr, channels=True)
    assert set(ch) >= {"RGB", "depth", "normal.RGB", "albedo.RGB", "object_id"}
    # the EXR holds exactly the rendered linear image
    ref = np.asarray(R.frame(S.load("spheres", overrides=SMALL), aovs=True)[0])
    assert np.array_equal(ch["RGB"], ref)
    from PIL import Image

    assert np.array_equal(np.asarray(Image.open(png)), image.to_srgb8(ref, exposure=0.5))


def test_spheres_scene_is_finite():
    _check_finite("spheres")  # compiled by the CLI test above when run in order


def test_cli_default_outputs_in_cwd(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert cli.main(["render", "spheres", "--width", "24", "--height", "24", "-q"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spheres.exr", "spheres.png"]
    assert capsys.readouterr().out == ""


@pytest.mark.parametrize(
    "argv,needle",
    [
        (["render", "no_such_scene"], "no such scene file"),
        (["render", "spheres", "--width", "-4"], "[camera] width"),
        (["render", "spheres", "--spp", "0"], "[render] spp"),
        (["render", "spheres", "-o", "out.png"], "must end in .exr"),
        (["render", "spheres", "--png", "/no/such/dir/x.png"], "does not exist"),
    ],
)
def test_cli_bad_input_is_one_line_exit_2(argv, needle, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxrt render: error:") and needle in err and "\n" not in err
    assert list(tmp_path.iterdir()) == []


def test_cli_help_documents_every_option(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["render", "--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    for opt in ("--output", "--png", "--width", "--height", "--spp", "--max-depth", "--seed", "--exposure",
                "--aovs", "Exit codes", "spheres"):
        assert opt in out


@pytest.mark.data
@pytest.mark.parametrize("name", ["bunny", "dragon", "cornell", "showcase"])
@pytest.mark.slow  # minutes on 2 cores: CI's slow pass
def test_data_scenes_are_finite(name, data_dir):
    _check_finite(name)
