"""The channel a coded image goes through (thesis Table 6.3's attacks, JPEG qualities,
noise levels) and the measures of chapter 6: PSNR, SSIM, the uncentred correlation
(6.6.1). Plain numpy/OpenCV, seeded where random."""

from __future__ import annotations

from typing import cast

import cv2
import numpy as np
import numpy.typing as npt


def jpeg(image: np.ndarray, quality: int) -> tuple[np.ndarray, int]:
    """(coded image after JPEG at ``quality``, its size [bytes])."""
    ok, data = cv2.imencode('.jpg', image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    # (not None: it decodes the JPEG just encoded)
    return cast(np.ndarray, cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)), int(data.size)


def jpeg_at_ratio(image: np.ndarray, ratio: float) -> tuple[np.ndarray, int]:
    """JPEG at the highest quality whose compression ratio (raw bytes / JPEG bytes) is at
    least ``ratio`` (A6.6: the thesis's "50:1", by bisection); (image, quality)."""
    low, high = 1, 100
    while low < high:
        quality = (low + high + 1) // 2
        if image.size / jpeg(image, quality)[1] >= ratio:
            low = quality
        else:
            high = quality - 1
    return jpeg(image, low)[0], low


def add_noise(image: np.ndarray, sigma: float, seed: int) -> npt.NDArray[np.uint8]:
    """Additive Gaussian noise of std ``sigma`` [grey levels], clipped to 8 bits."""
    noise = np.random.default_rng(seed).normal(0.0, sigma, image.shape)
    return np.clip(np.rint(image + noise), 0, 255).astype(np.uint8)


def resize_half_and_back(image: np.ndarray) -> np.ndarray:
    """Downscale a (H, W) image to half size (area) and back up to (H, W) (bilinear)."""
    H, W = image.shape
    half = cv2.resize(image, (W // 2, H // 2), interpolation=cv2.INTER_AREA)
    return cv2.resize(half, (W, H), interpolation=cv2.INTER_LINEAR)


def rotate(image: np.ndarray, degrees: float) -> np.ndarray:
    """Rotation about the centre, zero fill (A6.6: not rotated back)."""
    H, W = image.shape
    M = cv2.getRotationMatrix2D(((W - 1) / 2, (H - 1) / 2), degrees, 1.0)
    return cv2.warpAffine(image, M, (W, H), flags=cv2.INTER_LINEAR, borderValue=0)


def crop_centre(image: np.ndarray, area_fraction: float = 0.25) -> np.ndarray:
    """Zero a centred rectangle of ``area_fraction`` of the image (A6.6)."""
    out = image.copy()
    H, W = image.shape
    h, w = int(round(H * np.sqrt(area_fraction))), int(round(W * np.sqrt(area_fraction)))
    top, left = (H - h) // 2, (W - w) // 2
    out[top : top + h, left : left + w] = 0
    return out


def thesis_attacks(image: np.ndarray, seed: int = 0) -> dict[str, np.ndarray]:
    """{name: attacked image} for Table 6.3's seven attacks, settings as A6.6 decides."""
    return {
        'average 3x3': cv2.blur(image, (3, 3)),
        'median 3x3': cv2.medianBlur(image, 3),
        'noise 50 %': add_noise(image, 0.5 * float(np.std(image)), seed),
        'JPEG 50:1': jpeg_at_ratio(image, 50.0)[0],
        'resize 1/2': resize_half_and_back(image),
        'rotation 10 deg': rotate(image, 10.0),
        'crop 25 %': crop_centre(image),
    }


def extra_attacks(image: np.ndarray, seed: int = 0) -> dict[str, np.ndarray]:
    """{name: attacked image}: JPEG quality 90/70/50/30, noise 0.01/0.03/0.05 of 255."""
    out = {f'JPEG q{q}': jpeg(image, q)[0] for q in (90, 70, 50, 30)}
    for fraction in (0.01, 0.03, 0.05):
        out[f'noise {fraction:.2f}'] = add_noise(image, fraction * 255.0, seed)
    return out


def psnr(a: npt.ArrayLike, b: npt.ArrayLike) -> float:
    """PSNR [dB] of two 8-bit images (inf if equal)."""
    mse = np.mean((np.asarray(a, float) - np.asarray(b, float)) ** 2)
    return float('inf') if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def ssim(a: npt.ArrayLike, b: npt.ArrayLike) -> float:
    """Mean SSIM (Wang et al. 2004: Gaussian window sigma 1.5, K1 0.01, K2 0.03)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    blur = lambda x: cv2.GaussianBlur(x, (11, 11), 1.5)  # noqa: E731
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    s = (2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return float(s.mean())


def correlation(w: npt.ArrayLike, w_extracted: npt.ArrayLike) -> float:
    """(6.6.1) with A6.5: sum w w' / sqrt(sum w'^2 sum w^2) over min(M, N) values; 0 if
    either is all zero."""
    w, e = np.asarray(w, float), np.asarray(w_extracted, float)
    n = min(w.size, e.size)
    w, e = w[:n], e[:n]
    denominator = np.sqrt(np.sum(w**2) * np.sum(e**2))
    return float(np.sum(w * e) / denominator) if denominator > 0 else 0.0
