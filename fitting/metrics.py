"""Image error metrics for fits: RMSE and CIEDE2000 colour differences.

The ΔE is colour-science's (`colour.delta_E(..., method="CIE 2000")` of `colour.XYZ_to_Lab` of
`colour.RGB_to_XYZ(..., "sRGB")`) with its arithmetic written out here, operation for operation, so the
values are colour-science's bit for bit (`tests/fitting/test_metrics.py` compares them) without its
import: `import colour` loads scipy and matplotlib, 1.3 s of CPU on a GPU host and 2-4 s on a small
CPU, more than a warm fit's solve. CIEDE2000: Sharma, Wu & Dalal, "The CIEDE2000 color-difference
formula: implementation notes, supplementary test data, and mathematical observations", Color Res.
Appl. 30(1), 2005.
"""

from __future__ import annotations

import numpy as np

# Renders are linear radiance with no natural white, so ΔE needs a reference: both images are divided
# by the target's 99th-percentile luminance (over the compared pixels) before sRGB-primaries RGB ->
# XYZ -> CIELAB (D65), i.e. the target's highlights sit at L* ≈ 100.
WHITE_PERCENTILE = 99.0

# IEC 61966-2-1's linear sRGB -> XYZ matrix (its 4-digit values, as colour-science's sRGB colourspace
# holds them), then the CAT02 adaptation colour-science's `RGB_to_XYZ` applies by default, from the
# sRGB whitepoint to the same whitepoint: inv(M_CAT02) · diag(1) · M_CAT02, which float64 leaves a few
# ulps from the identity; both products are kept so the values match colour-science's exactly.
_SRGB_TO_XYZ = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
_CAT02_SELF = np.array([[1.0, -2.925337592710602e-17, -2.0424934209769367e-17],
                        [1.865516512262643e-17, 1.0, -6.012863655103287e-19],
                        [-1.1925326645651568e-18, -6.805220268068795e-19, 1.0]])
# D65 (CIE 1931 2°, xy = 0.3127, 0.3290) as XYZ with Y = 1: the CIELAB reference white
_D65_XYZ = np.array([0.9504559270516716, 1.0, 1.0890577507598784])


def rmse(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Root-mean-square difference over the (masked) pixels and channels of (…, 3) images."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    if mask is not None:
        d = d[np.asarray(mask, bool)]
    return float(np.sqrt(np.mean(d**2))) if d.size else 0.0


def _vecmul(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.matmul(m, v[..., None]).squeeze(-1)


def _f(t: np.ndarray) -> np.ndarray:
    """CIE 1976's lightness function of a ratio to the white: a cube root above (24/116)³, linear below."""
    cube_root = np.sign(t) * np.abs(t) ** np.asarray(1 / 3)
    return np.where(t > (24 / 116) ** 3, cube_root, (841 / 108) * t + 16 / 116)


def _lab(rgb: np.ndarray, white: float) -> np.ndarray:
    """CIELAB (D65) of linear sRGB-primaries values divided by `white`, (…, 3)."""
    rgb = np.asarray(rgb, np.float64) / white
    xyz = _vecmul(_CAT02_SELF, _vecmul(_SRGB_TO_XYZ, rgb))
    fx, fy, fz = (_f(xyz[..., i] / _D65_XYZ[i]) for i in range(3))
    return np.stack([116 * fy - 16, 500 * (fx - fy), 200 * (fy - fz)], axis=-1)


def _hue(b: np.ndarray, a: np.ndarray) -> np.ndarray:
    return np.where(np.logical_and(b == 0, a == 0), 0, np.degrees(np.arctan2(b, a)) % 360)


def ciede2000(lab1: np.ndarray, lab2: np.ndarray) -> np.ndarray:
    """CIEDE2000 ΔE between CIELAB arrays (…, 3), k_L = k_C = k_H = 1 (Sharma et al. 2005, eqs. 1-22)."""
    L_1, a_1, b_1 = (np.asarray(lab1, np.float64)[..., i] for i in range(3))
    L_2, a_2, b_2 = (np.asarray(lab2, np.float64)[..., i] for i in range(3))
    C_bar_ab = (np.hypot(a_1, b_1) + np.hypot(a_2, b_2)) / 2
    C_bar_ab_7 = C_bar_ab**7
    G = 0.5 * (1 - np.sqrt(C_bar_ab_7 / (C_bar_ab_7 + 25**7)))
    a_p_1, a_p_2 = (1 + G) * a_1, (1 + G) * a_2
    C_p_1, C_p_2 = np.hypot(a_p_1, b_1), np.hypot(a_p_2, b_2)
    h_p_1, h_p_2 = _hue(b_1, a_p_1), _hue(b_2, a_p_2)
    delta_L_p = L_2 - L_1
    delta_C_p = C_p_2 - C_p_1
    h_p_2_s_1 = h_p_2 - h_p_1
    C_p_1_m_2 = C_p_1 * C_p_2
    delta_h_p = np.select([C_p_1_m_2 == 0, np.fabs(h_p_2_s_1) <= 180, h_p_2_s_1 > 180, h_p_2_s_1 < -180],
                          [0, h_p_2_s_1, h_p_2_s_1 - 360, h_p_2_s_1 + 360])
    delta_H_p = 2 * np.sqrt(C_p_1_m_2) * np.sin(np.deg2rad(delta_h_p / 2))
    L_bar_p = (L_1 + L_2) / 2
    C_bar_p = (C_p_1 + C_p_2) / 2
    a_h_p_1_s_2 = np.fabs(h_p_1 - h_p_2)
    h_p_1_a_2 = h_p_1 + h_p_2
    h_bar_p = np.select(
        [C_p_1_m_2 == 0, a_h_p_1_s_2 <= 180, np.logical_and(a_h_p_1_s_2 > 180, h_p_1_a_2 < 360),
         np.logical_and(a_h_p_1_s_2 > 180, h_p_1_a_2 >= 360)],
        [h_p_1_a_2, h_p_1_a_2 / 2, (h_p_1_a_2 + 360) / 2, (h_p_1_a_2 - 360) / 2])
    T = (1 - 0.17 * np.cos(np.deg2rad(h_bar_p - 30)) + 0.24 * np.cos(np.deg2rad(2 * h_bar_p))
         + 0.32 * np.cos(np.deg2rad(3 * h_bar_p + 6)) - 0.20 * np.cos(np.deg2rad(4 * h_bar_p - 63)))
    delta_theta = 30 * np.exp(-(((h_bar_p - 275) / 25) ** 2))
    C_bar_p_7 = C_bar_p**7
    R_C = 2 * np.sqrt(C_bar_p_7 / (C_bar_p_7 + 25**7))
    L_bar_p_2 = (L_bar_p - 50) ** 2
    S_L = 1 + ((0.015 * L_bar_p_2) / np.sqrt(20 + L_bar_p_2))
    S_C = 1 + 0.045 * C_bar_p
    S_H = 1 + 0.015 * C_bar_p * T
    R_T = -np.sin(np.deg2rad(2 * delta_theta)) * R_C
    k_L = k_C = k_H = 1
    return np.sqrt((delta_L_p / (k_L * S_L)) ** 2 + (delta_C_p / (k_C * S_C)) ** 2 + (delta_H_p / (k_H * S_H)) ** 2
                   + R_T * (delta_C_p / (k_C * S_C)) * (delta_H_p / (k_H * S_H)))


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
    return np.asarray(ciede2000(_lab(fit, white), _lab(target, white)))
