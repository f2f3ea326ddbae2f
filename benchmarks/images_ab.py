"""Render every shipped scene small with both integrators and AOVs, or compare two such sets bit for bit
(before/after a change that must not change images).

    JAXRT_DATA=../shared/data/meshes python benchmarks/images_ab.py save OUT_DIR [--size 48x36]
    python benchmarks/images_ab.py compare BEFORE_DIR AFTER_DIR

`save` works on any tree that has `jaxrt.render(name, aovs=True, overrides=...)`; run it with that
tree's root on PYTHONPATH. `compare` prints, per scene and integrator, `=` for every bit-identical
array, else the largest difference and the fraction of differing values.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def save(out: Path, size: str) -> int:
    import jaxrt

    w, h = (int(x) for x in size.split("x"))
    scenes = Path(jaxrt.__file__).resolve().parents[1] / "scenes"
    out.mkdir(parents=True, exist_ok=True)
    for path in sorted(scenes.glob("*.toml")):
        for integ in ("whitted", "path"):
            ov = {"camera.width": w, "camera.height": h, "render.integrator": integ, "render.spp": 1}
            try:
                img, aov = jaxrt.render(path.stem, aovs=True, overrides=ov)
            except Exception as e:  # a tree that cannot render a case: say so and go on
                print(f"{path.stem} {integ}: {type(e).__name__}: {str(e)[:120]}")
                continue
            np.savez(out / f"{path.stem}_{integ}.npz", image=np.asarray(img), **{k: np.asarray(v) for k, v in aov.items()})
            print(f"{path.stem} {integ}: mean {float(np.asarray(img).mean()):.6f}")
    return 0


def compare(a_dir: Path, b_dir: Path) -> int:
    bad = 0
    for f in sorted(a_dir.glob("*.npz")):
        g = b_dir / f.name
        if not g.exists():
            print(f"{f.stem}: missing in {b_dir}")
            bad += 1
            continue
        a, b = np.load(f), np.load(g)
        cols = []
        for k in a.files:
            x, y = a[k], b[k]
            if x.shape != y.shape:
                cols.append(f"{k}: shape {x.shape} vs {y.shape}")
            elif np.array_equal(x, y):
                cols.append(f"{k} =")
            else:
                d = np.abs(x.astype(np.float64) - y.astype(np.float64)).max()
                cols.append(f"{k}: max |diff| {d:.2e}, {np.mean(x != y):.4f} differ")
            bad += not cols[-1].endswith("=")
        print(f"{f.stem}: " + ", ".join(cols))
    return 1 if bad else 0


def main() -> int:
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("save")
    s.add_argument("out", type=Path)
    s.add_argument("--size", default="48x36")
    c = sub.add_parser("compare")
    c.add_argument("before", type=Path)
    c.add_argument("after", type=Path)
    args = ap.parse_args()
    return save(args.out, args.size) if args.cmd == "save" else compare(args.before, args.after)


if __name__ == "__main__":
    sys.exit(main())
