"""Every ```python block of README.md runs as written, so the examples cannot rot.

Each block runs in its own Python subprocess, in a fresh temporary folder (examples may write files
such as lobe.png there). The only change made to a block is its image size: every
`"camera.width": N` and `"camera.height": N` becomes 16 and 12, so a block that renders or fits runs
in seconds on a CPU. Blocks that use the Stanford meshes (a data name such as "bunny", or
`data.find`) need JAXRT_DATA and skip without it, like the other data tests.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
SIZES = {"camera.width": 16, "camera.height": 12}
DATA_NAMES = ("data.find(", '"bunny"', '"dragon"', '"cornell"', '"cornell_area"', '"showcase"', '"bunnies"')


def python_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def small(code: str) -> str:
    for key, value in SIZES.items():
        code = re.sub(rf'"{re.escape(key)}":\s*\d+', f'"{key}": {value}', code)
    return code


BLOCKS = python_blocks(README.read_text())


def test_the_readme_has_python_examples():
    assert len(BLOCKS) >= 5
    assert small('{"camera.width": 256, "camera.height": 192}') == '{"camera.width": 16, "camera.height": 12}'


SLOW_EXAMPLES = ("grad(", "fit_measured(", "sppm.")


def _param(block: str):
    # examples that compile a minute or more on 2 cores (the renderer's gradient, a batched measured
    # fit, photon-mapping passes) run in the slow pass
    marks = [pytest.mark.slow] if any(k in block for k in SLOW_EXAMPLES) else []
    return pytest.param(block, marks=marks, id=block.strip().splitlines()[-1][:40])


@pytest.mark.parametrize("code", [_param(b) for b in BLOCKS])
def test_readme_example_runs(code, tmp_path):
    if any(n in code for n in DATA_NAMES) and not os.environ.get("JAXRT_DATA"):
        pytest.skip("the example uses the Stanford meshes and JAXRT_DATA is not set")
    # this checkout first on the path (the interpreter's installed jaxrt may be another checkout)
    path = os.pathsep.join([str(ROOT)] + ([os.environ["PYTHONPATH"]] if os.environ.get("PYTHONPATH") else []))
    proc = subprocess.run([sys.executable, "-c", small(code)], cwd=tmp_path, capture_output=True, text=True,
                          timeout=900, env={**os.environ, "MPLBACKEND": "Agg", "PYTHONPATH": path})
    assert proc.returncode == 0, f"README example failed:\n{code}\n--- stderr:\n{proc.stderr[-4000:]}"


def test_the_readme_model_table_matches_the_parameter_declarations():
    """Each row of README's BRDF table gives every parameter's default, bounds, scale and RGB-ness as
    declared once in `brdfs` (`Param`), and lists every registered model: the table is checked, not
    trusted, since it is written by hand."""
    import re

    import brdfs

    rows = {}
    for line in README.read_text().splitlines():
        m = re.match(r"\| (\w+)(?: \(delta\))? \| (.+?) \| .+ \| .+ \|$", line)
        if m and m.group(1) in brdfs.names():
            rows[m.group(1)] = m.group(2)
    assert sorted(rows) == sorted(brdfs.names())
    for name, cell in rows.items():
        seen = {}
        for group in re.sub(r"\([^)]*\)", "", cell).split(";"):  # remarks in parentheses dropped
            g = re.match(r"\s*(.*?)\[([^,\]]+),([^\]]+)\]\s*(.*)$", group)
            assert g, (name, group)
            lo, hi, flags = float(g.group(2)), float(g.group(3)), g.group(4).split()
            for pname, default in re.findall(r"(\w+) ([-\d.e+]+)", g.group(1)):
                seen[pname] = (float(default), lo, hi, "log" if "log" in flags else "linear", "rgb" in flags)
        declared = {p.name: (p.default, p.lo, p.hi, p.scale, p.rgb) for p in brdfs.get(name).spec}
        assert seen == declared, name
