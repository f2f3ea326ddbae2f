"""Image error metrics for fits: RMSE and CIEDE2000 colour differences (through colour-science)."""

from __future__ import annotations

import threading

import numpy as np

# Renders are linear radiance with no natural white, so ΔE needs a reference: both images are divided
# by the target's 99th-percentile luminance (over the compared pixels) before sRGB-primaries RGB ->
# XYZ -> CIELAB (D65), i.e. the target's highlights sit at L* ≈ 100.
WHITE_PERCENTILE = 99.0


def prefetch() -> None:
    """Start importing colour-science in a background thread (once per process), so the ΔE at the end
    of a fit does not wait for it.

    `import colour` also imports its plotting module and with it matplotlib.pyplot and scipy: 1.3 s on
    an H200 host, 2-4 s on a busy 2-core CPU. A fit mostly waits on compiled code, outside the
    interpreter lock, so the import overlaps it; `delta_e_2000` then finds the module imported."""
    global _prefetch
    with _prefetch_lock:
        if _prefetch is None:
            _prefetch = threading.Thread(target=_import_colour, name="fitting-import-colour", daemon=True)
            _prefetch.start()


def _import_colour():
    try:
        import colour  # noqa: F401
    except Exception:  # noqa: BLE001 -- the import in delta_e_2000 reports it
        pass


_prefetch: threading.Thread | None = None
_prefetch_lock = threading.Lock()


def rmse(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Root-mean-square difference over the (masked) pixels and channels of (…, 3) images."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    if mask is not None:
        d = d[np.asarray(mask, bool)]
    return float(np.sqrt(np.mean(d**2))) if d.size else 0.0


def _lab(rgb: np.ndarray, white: float) -> np.ndarray:
    import colour  # loaded where first used: it takes ~1.5 s to import (scipy, matplotlib)

    rgb = np.asarray(rgb, np.float64) / white
    xyz = colour.RGB_to_XYZ(rgb, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_decoding=False)
    return colour.XYZ_to_Lab(xyz, colour.RGB_COLOURSPACES["sRGB"].whitepoint)


def delta_e_2000(fit: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Per-pixel CIEDE2000 ΔE between two linear-RGB images (…, 3); returns the masked pixels' values."""
    fit = np.asarray(fit, np.float64).reshape(-1, 3)
    target = np.asarray(target, np.float64).reshape(-1, 3)
    if mask is not None:
        m = np.asarray(mask, bool).reshape(-1)
        fit, target = fit[m], target[m]
    if not len(target):
        return np.zeros(0)
    lum = target @ np.array([0.2126, 0.7152, 0.0722])
    white = max(float(np.percentile(lum, WHITE_PERCENTILE)), 1e-12)
    import colour

    return np.asarray(colour.delta_E(_lab(fit, white), _lab(target, white), method="CIE 2000"))
