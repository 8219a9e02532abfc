"""Procedural textures of the synthetic room: one periodic stack of band-limited noise and
pattern images shared by all materials, and its mip atlas for trilinear lookups.

Textures are laid on each face's plane in world coordinates (shifted and scaled per
material, see recon.synthetic.room.Materials), so the albedo of a point depends only on
the point and its object.
"""

from __future__ import annotations

import cv2
import numpy as np
import scipy.fft

# Textures: one periodic image stack shared by all materials, 4 mm texels, 8.192 m period
# (a power of two, so checker and stripe periods tile it exactly).
TEXEL = 0.004
TEXTURE_SIZE = 2048
TEXTURE_PERIOD = TEXEL * TEXTURE_SIZE
_TEXTURE_LEVELS = 7  # mip levels down to 25.6 cm texels: enough for grazing views at low resolution
_CHECKER_PERIOD = 0.512  # 25.6 cm tiles
_STRIPE_PERIOD = 0.128


def _frequency_grid() -> np.ndarray:
    """(S, S//2+1) radial frequency in cycles/metre of an rfft2 of a level-0 texture."""
    fy = np.fft.fftfreq(TEXTURE_SIZE, d=TEXEL).astype(np.float32)
    fx = np.fft.rfftfreq(TEXTURE_SIZE, d=TEXEL).astype(np.float32)
    return np.sqrt(fy[:, None] ** 2 + fx[None, :] ** 2)


def _noise_spectrum(rng: np.random.Generator, freq: np.ndarray, shortest: float, longest: float) -> np.ndarray:
    """rfft2 (S, S//2+1) of periodic noise with equal energy per octave between the wavelengths."""
    white = rng.standard_normal((TEXTURE_SIZE, TEXTURE_SIZE), dtype=np.float32)
    f = np.maximum(freq, np.float32(1e-3))
    # 1/f amplitude = equal energy per octave in 2-D; the band edges are soft (logistic in
    # log frequency) to avoid ringing.
    low, high = np.float32(1.0 / longest), np.float32(1.0 / shortest)
    gain = 1.0 / (f * (1.0 + (low / f) ** 4) * (1.0 + (f / high) ** 4))
    spectrum = scipy.fft.rfft2(white, workers=-1)
    spectrum *= gain
    spectrum[0, 0] = 0.0
    return spectrum


def _pattern_spectra() -> tuple[np.ndarray, np.ndarray]:
    """rfft2 of a 0/1 checkerboard (varying along both axes) and of 0/1 stripes along u."""
    x = (np.arange(TEXTURE_SIZE) + 0.5) * TEXEL
    checker_1d = np.floor(x / (_CHECKER_PERIOD / 2)) % 2
    stripes_1d = (np.floor(x / (_STRIPE_PERIOD / 2)) % 2).astype(np.float32)
    checker = (checker_1d[:, None] != checker_1d[None, :]).astype(np.float32)
    stripes = np.ascontiguousarray(np.broadcast_to(stripes_1d[None, :], (TEXTURE_SIZE, TEXTURE_SIZE)))
    return scipy.fft.rfft2(checker, workers=-1), scipy.fft.rfft2(stripes, workers=-1)


def _crop(spectrum: np.ndarray, size: int) -> np.ndarray:
    """The (size, size//2+1) low-frequency corner block of a full rfft2 layout."""
    half = size // 2
    return np.concatenate([spectrum[:half, : half + 1], spectrum[-half:, : half + 1]])


def _mip_level(spectra: list[np.ndarray], freq: np.ndarray, level: int) -> np.ndarray:
    """Band-limited images (s, s, C) float32 at mip `level` (texel TEXEL * 2^level) from full rfft2s."""
    size = TEXTURE_SIZE >> level
    nyquist = 0.5 / (TEXEL * 2**level)
    # A Gaussian roll-off to ~5% at the level's Nyquist frequency keeps bilinear lookups alias-free.
    gain = np.exp(-0.5 * (_crop(freq, size) / (nyquist / 2.5)) ** 2) * np.float32((size / TEXTURE_SIZE) ** 2)
    out = np.empty((size, size, len(spectra)), dtype=np.float32)
    for c, spectrum in enumerate(spectra):
        out[..., c] = scipy.fft.irfft2(_crop(spectrum, size) * gain, s=(size, size), workers=-1)
    return out


def texture_pyramid(seed: int) -> list[np.ndarray]:
    """Mip levels of the shared texture stack, level k of shape (S/2^k, S/2^k, 4) float32.

    Channels: fine luminance noise (2 cm - 50 cm features, unit std), coarse colour-mix
    noise (5 cm - 80 cm, unit std), checkerboard and stripes (both ~0/1). Texel (i, j) of
    level k sits at (u, v) = (j, i) * TEXEL * 2^k; the stack is periodic with TEXTURE_PERIOD.
    """
    rng = np.random.default_rng([seed, 2])
    freq = _frequency_grid()
    spectra = [_noise_spectrum(rng, freq, 0.02, 0.5), _noise_spectrum(rng, freq, 0.05, 0.8), *_pattern_spectra()]
    levels = [_mip_level(spectra, freq, k) for k in range(_TEXTURE_LEVELS)]
    for c in (0, 1):
        std = levels[0][..., c].std()
        for image in levels:
            image[..., c] /= std
    return levels


class MipAtlas:
    """All mip levels in one image, each wrapped by a 1-texel periodic border, so that a
    whole batch of trilinear lookups is two cv2.remap calls.

    Layout: level 0 at the left, the smaller levels stacked in a column to its right.
    """

    def __init__(self, pyramid: list[np.ndarray]):
        sizes = [p.shape[0] for p in pyramid]
        height = sizes[0] + 2
        width = sizes[0] + 2 + (sizes[1] + 2 if len(sizes) > 1 else 0)
        self.image = np.zeros((height, width, pyramid[0].shape[2]), dtype=np.float32)
        origins = []
        x, y = sizes[0] + 2, 0
        for k, level in enumerate(pyramid):
            ox, oy = (0, 0) if k == 0 else (x, y)
            padded = np.pad(level, ((1, 1), (1, 1), (0, 0)), mode="wrap")
            self.image[oy : oy + sizes[k] + 2, ox : ox + sizes[k] + 2] = padded
            origins.append((ox + 1, oy + 1))
            if k > 0:
                y += sizes[k] + 2
        origin = np.array(origins, dtype=np.float32)
        self.origin_x, self.origin_y = origin[:, 0].copy(), origin[:, 1].copy()  # (L,) atlas position of texel (0, 0)
        self.inv_texel = (1.0 / (TEXEL * 2.0 ** np.arange(len(sizes)))).astype(np.float32)  # (L,) texels per metre
        self.levels = len(sizes)

    def sample(self, u: np.ndarray, v: np.ndarray, level: np.ndarray) -> np.ndarray:
        """Trilinear lookup (P, C) at texture-plane metres u, v (P,) and fractional mip level (P,)."""
        level = np.clip(level, 0.0, self.levels - 1.001).astype(np.float32)
        base = level.astype(np.int32)
        weight = (level - base)[:, None]
        # Every level has the same period in metres, so wrap once here.
        period = np.float32(TEXTURE_PERIOD)
        u = u - np.floor(u / period) * period
        v = v - np.floor(v / period) * period
        out = self._bilinear(u, v, base)
        out += (self._bilinear(u, v, base + 1) - out) * weight
        return out

    def _bilinear(self, u: np.ndarray, v: np.ndarray, level: np.ndarray) -> np.ndarray:
        scale = self.inv_texel[level]
        x = u * scale + self.origin_x[level]
        y = v * scale + self.origin_y[level]
        # cv2.remap wants 2-D maps with sides below SHRT_MAX: lay the points out in rows.
        n, cols = len(u), 1024
        if n % cols:
            pad = cols - n % cols
            x, y = np.concatenate([x, np.zeros(pad, np.float32)]), np.concatenate([y, np.zeros(pad, np.float32)])
        out = cv2.remap(self.image, x.reshape(-1, cols), y.reshape(-1, cols), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(-1, self.image.shape[2])[:n]
