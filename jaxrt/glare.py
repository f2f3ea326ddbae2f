"""Glare: diffraction by the camera's aperture, a post-process of the linear HDR image.

A lens of focal length f whose aperture (pupil) is the mask A images a distant point source as the
Fraunhofer diffraction pattern of A: the point-spread function PSF(x) ∝ |Â(x / (λ f))|², the squared
modulus of the Fourier transform of the aperture, scaled by the wavelength λ (Goodman, "Introduction
to Fourier Optics", 3rd ed. 2005, §4.3 and §6.2). Ritschel, Ihrke, Frisvad, Seidel and Myszkowski,
"Temporal Glare: Real-Time Dynamic Simulation of the Scattering in the Human Eye" (Eurographics
2009) compute it the same way, with an FFT of an aperture image, and convolve the image with it by
FFT. Here:

- The aperture is a circle or a regular polygon of `blades` straight blades (inscribed in the circle
  of diameter f / N), rasterised with an anti-aliased edge (coverage from the signed distance).
- Units: with a sensor of pixel pitch p, an f-number N and the mask sampled M times across a grid
  of width M·δ, the FFT's frequency bin k is the image-plane offset k·λf / (M·δ). Choosing
  M = s·K (the PSF's width K in pixels, s = `OVERSAMPLE` samples per pixel) and δ = λf / (K·p) puts s
  bins in each pixel, and the aperture's diameter f / N is D = K·p / (λ·N) samples. A circle then gives
  the Airy pattern, whose first dark ring has the radius 1.21967·λN/p pixels (the first zero of J1
  over π), 1.22·λN/p in the usual rounding. Each RGB channel uses its own wavelength
  (`WAVELENGTHS`: 650, 550, 450 nm) through D, which is the radial rescaling of the PSF by
  λ / λ_ref that Ritschel et al. apply to one computed PSF, done exactly.
- The PSF is integrated over each pixel (trapezoidal weights over the s + 1 bins across it) and
  normalised to sum 1 per channel, so spreading light with it moves energy and never creates it.
  The FFT's PSF is periodic with period K pixels: the tails beyond ±K/2 fold back into the window.
- The convolution runs by FFT on an image padded by K − 1 pixels (a linear convolution, no
  wrap-around between opposite edges). At the borders, the part of a source pixel's PSF that would
  leave the frame is given back to the part inside (each source pixel's spread is renormalised by
  the PSF mass that lands in the frame, computed exactly from a summed-area table of the PSF), so
  the image sum is preserved. (A real sensor loses that light, and gains light from sources outside
  the frame, which a rendered frame does not have.)
- Either the whole image is spread (`threshold = 0`, the physical case: every pixel diffracts), or
  only the light above a luminance `threshold`: a pixel of luminance Y > threshold gives the
  fraction (Y − threshold) / Y of its RGB to the spread, keeping its colour. `strength` scales that
  fraction. What the bright pixels lose is exactly what is spread, so energy is preserved in both
  cases.

The computation is float32 `jnp.fft` under one `jax.jit` per (image shape, `Glare`): every setting
is static (it fixes the PSF and the FFT sizes). FFT round-off adds noise of about 1e-7 times the
brightest pixel to every pixel; very dark regions next to very bright sources may show it (and it
may be slightly negative).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrt.errors import InputError

__all__ = ["APERTURES", "FIELDS", "OVERSAMPLE", "WAVELENGTHS", "Glare", "airy_radius", "apply", "psf",
           "work_bytes"]

#: Aperture shapes, default first.
APERTURES = ("polygon", "circle")
#: The wavelength [m] each linear RGB channel is diffracted at (red, green, blue); green is the
#: reference that `airy_radius` and messages quote.
WAVELENGTHS = (650e-9, 550e-9, 450e-9)
#: FFT bins per pixel when computing the PSF (the mask grid is OVERSAMPLE × size samples wide).
OVERSAMPLE = 4
# Rec. 709 luminance of linear RGB, for the threshold.
_LUMA = (0.2126, 0.7152, 0.0722)

#: Every setting: name -> (default, lo, hi, kind, meaning). Scene files' [glare] table, the CLI's
#: --glare and `Glare` itself read their ranges here.
FIELDS = {
    "aperture": ("polygon", None, None, "choice", "aperture shape: " + " | ".join(APERTURES)),
    "blades": (6, 3, 32, "int", "polygon aperture: number of straight blades"),
    "rotation": (0.0, -360.0, 360.0, "float", "polygon aperture: rotation in degrees"),
    "f_number": (16.0, 0.5, 1024.0, "float", "f-number N (focal length / aperture diameter)"),
    "pixel_pitch": (4.0, 0.1, 100.0, "float", "sensor pixel pitch p in micrometres"),
    "size": (255, 15, 1023, "odd", "width of the PSF in pixels (odd)"),
    "threshold": (0.0, 0.0, 1e18, "float", "luminance above which light is spread (0: the whole image)"),
    "strength": (1.0, 0.0, 1.0, "float", "fraction of the light above the threshold that is spread"),
}
# The Airy radius at 650 nm (the widest PSF) is at most size / MIN_SPAN pixels, so that the
# pattern's first rings fit in the window and the aperture spans at least 1.22·MIN_SPAN samples;
# the radius at 450 nm (the narrowest) is at least MIN_AIRY pixels, so that the aperture spans at
# most half the mask grid (the PSF, band-limited to twice the aperture, is then sampled without
# aliasing).
MIN_SPAN, MIN_AIRY = 8, 0.61


@dataclasses.dataclass(frozen=True)
class Glare:
    """Glare settings (hashable: one compiled program per image shape and settings).

    Attributes are `FIELDS`'s: aperture ("polygon" | "circle"), blades, rotation [degrees],
    f_number, pixel_pitch [µm], size [pixels, odd], threshold [luminance], strength [0, 1].
    Bad values raise InputError (one line naming the setting and what is allowed).
    """

    aperture: str = FIELDS["aperture"][0]
    blades: int = FIELDS["blades"][0]
    rotation: float = FIELDS["rotation"][0]
    f_number: float = FIELDS["f_number"][0]
    pixel_pitch: float = FIELDS["pixel_pitch"][0]
    size: int = FIELDS["size"][0]
    threshold: float = FIELDS["threshold"][0]
    strength: float = FIELDS["strength"][0]

    def __post_init__(self):
        for name, (_, lo, hi, kind, _doc) in FIELDS.items():
            v = getattr(self, name)
            if kind == "choice":
                if v not in APERTURES:
                    raise InputError(f"glare: aperture {v!r} is not allowed; allowed: {', '.join(APERTURES)}")
                continue
            ok_type = isinstance(v, int) if kind in ("int", "odd") else isinstance(v, (int, float))
            if isinstance(v, bool) or not ok_type or not (lo <= v <= hi) or (kind == "odd" and v % 2 == 0):
                what = {"int": "an integer", "odd": "an odd integer", "float": "a number"}[kind]
                raise InputError(f"glare: {name} = {v!r}: expected {what} in [{lo:g}, {hi:g}]")
            if kind == "float":
                object.__setattr__(self, name, float(v))
        red, blue = airy_radius(self, WAVELENGTHS[0]), airy_radius(self, WAVELENGTHS[2])
        if red > self.size / MIN_SPAN:
            raise InputError(f"glare: the Airy radius 1.22·λN/p at 650 nm is {red:.3g} pixels, more than "
                             f"size / {MIN_SPAN} = {self.size / MIN_SPAN:g}: lower f_number, raise pixel_pitch "
                             "or raise size")
        if blue < MIN_AIRY:
            raise InputError(f"glare: the Airy radius 1.22·λN/p at 450 nm is {blue:.3g} pixels, less than "
                             f"{MIN_AIRY:g} (diffraction finer than a pixel): raise f_number or lower pixel_pitch")


def airy_radius(g: Glare, wavelength: float = WAVELENGTHS[1]) -> float:
    """The radius in pixels of the first dark ring of the circular aperture's Airy pattern: 1.21967·λN/p
    (the first zero of the Bessel function J1, 3.8317, over π)."""
    return 3.831705970207512 / math.pi * wavelength * g.f_number / (g.pixel_pitch * 1e-6)


def _aperture(g: Glare, diameter: float, m: int) -> Float[Array, "m m"]:
    """Coverage in [0, 1] of the aperture of `diameter` samples, centred in an m × m grid, with an edge
    anti-aliased over one sample (0.5 − signed distance, clipped)."""
    x = jnp.arange(m, dtype=jnp.float32) - m // 2
    px, py = x[None, :], x[:, None]
    r = diameter / 2
    if g.aperture == "circle":
        dist = jnp.sqrt(px * px + py * py) - r
    else:  # a regular polygon inscribed in the circle: the largest signed distance to its edge lines
        n = g.blades
        phi = math.radians(g.rotation) + 2 * math.pi * np.arange(n) / n
        c, s = jnp.asarray(np.cos(phi), jnp.float32), jnp.asarray(np.sin(phi), jnp.float32)
        dist = jnp.max(px[..., None] * c + py[..., None] * s, axis=-1) - r * math.cos(math.pi / n)
    return jnp.clip(0.5 - dist, 0.0, 1.0)


def _psf(g: Glare) -> Float[Array, "3 K K"]:
    k, s = g.size, OVERSAMPLE
    m = s * k
    out = []
    for lam in WAVELENGTHS:
        diameter = k * g.pixel_pitch * 1e-6 / (lam * g.f_number)
        a = _aperture(g, diameter, m)
        intensity = jnp.fft.fftshift(jnp.abs(jnp.fft.fft2(a)) ** 2)  # zero frequency at m // 2
        # integrate over pixels: trapezoidal weights over the s + 1 bins across each pixel (symmetric
        # about the pixel's centre; the spectrum is periodic, so the rolls are exact)
        for axis in (0, 1):
            intensity = sum(wt * jnp.roll(intensity, sh, axis=axis)
                            for sh, wt in ((-2, 0.5), (-1, 1.0), (0, 1.0), (1, 1.0), (2, 0.5)))
        # pixel j's centre is bin m // 2 + (j − k // 2)·s, which is 2 + s·j for odd k and s = 4
        start = m // 2 - (k // 2) * s
        p = intensity[start::s, start::s][:k, :k]
        out.append(p / jnp.sum(p))
    return jnp.stack(out)


@functools.partial(jax.jit, static_argnames=("g",))
def _psf_jit(g):
    return _psf(g)


def psf(g: Glare) -> Float[Array, "3 K K"]:
    """The per-channel (R, G, B) point-spread function, `g.size` pixels square, centred at
    (size // 2, size // 2), each channel summing to 1."""
    return _psf_jit(g)


def _fast_len(n: int) -> int:
    """The smallest 2^a·3^b·5^c ≥ n (FFT lengths that pocketfft/cuFFT handle fastest)."""
    best = 1 << (n - 1).bit_length()
    p5 = 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            q = p35
            while q < n:
                q *= 2
            best = min(best, q)
            p35 *= 3
        p5 *= 5
    return best


def _frame_mass(p: Float[Array, "3 K K"], h: int, w: int) -> Float[Array, "3 h w"]:
    """For each source pixel, the PSF mass that lands inside the h × w frame: rectangle sums of a
    summed-area table of the PSF (exact up to float32 rounding)."""
    k = p.shape[-1]
    c = k // 2
    sat = jnp.pad(jnp.cumsum(jnp.cumsum(p, axis=1), axis=2), ((0, 0), (1, 0), (1, 0)))
    rows, cols = np.arange(h), np.arange(w)
    a0, a1 = np.clip(c - rows, 0, k), np.clip(c + h - rows, 0, k)
    b0, b1 = np.clip(c - cols, 0, k), np.clip(c + w - cols, 0, k)

    def at(a, b):
        return sat[:, a[:, None], b[None, :]]

    return at(a1, b1) - at(a0, b1) - at(a1, b0) + at(a0, b0)


@functools.partial(jax.jit, static_argnames=("g",))
def _apply(image, g):
    h, w, _ = image.shape
    p = _psf(g)
    k = g.size
    img = jnp.moveaxis(image.astype(jnp.float32), -1, 0)  # (3, h, w)
    luma = sum(wt * img[i] for i, wt in enumerate(_LUMA))
    if g.threshold > 0:
        frac = jnp.where(luma > g.threshold, 1.0 - g.threshold / jnp.where(luma > g.threshold, luma, 1.0), 0.0)
    else:
        frac = jnp.where(luma > 0, 1.0, 0.0)
    spread = (g.strength * frac)[None] * img
    # every source pixel's spread lands inside the frame in full (see the module docstring)
    src = spread / _frame_mass(p, h, w)
    hp, wp = _fast_len(h + k - 1), _fast_len(w + k - 1)
    full = jnp.fft.irfft2(jnp.fft.rfft2(src, s=(hp, wp)) * jnp.fft.rfft2(p, s=(hp, wp)), s=(hp, wp))
    c = k // 2
    out = img - spread + full[:, c:c + h, c:c + w]
    return jnp.moveaxis(out, 0, -1)


def apply(image: Float[Array, "H W 3"], g: Glare | None) -> Float[Array, "H W 3"]:
    """The image with the glare of `g` (None: the image itself, untouched). Linear RGB in, linear RGB
    out (float32, a JAX array), the same sum; differentiable with respect to the image."""
    if g is None:
        return image
    if not isinstance(g, Glare):
        raise TypeError(f"expected a jaxrt.glare.Glare or None, got {type(g).__name__}")
    if getattr(image, "ndim", None) != 3 or image.shape[-1] != 3:
        raise InputError(f"glare: expected an (H, W, 3) RGB image, got shape {getattr(image, 'shape', None)}")
    return _apply(image, g)


def work_bytes(height: int, width: int, g: Glare | None) -> int:
    """An upper estimate of the memory `apply` uses for an image of this size: the PSF's mask grid and
    spectra (three complex64 arrays of (OVERSAMPLE·size)²) and the padded complex spectra of the
    image and the PSF (complex64, three channels, a few live at once)."""
    if g is None:
        return 0
    m = OVERSAMPLE * g.size
    hp, wp = _fast_len(height + g.size - 1), _fast_len(width + g.size - 1)
    return 3 * 8 * m * m + 4 * 3 * 8 * hp * (wp // 2 + 1) + 4 * 3 * 4 * height * width
