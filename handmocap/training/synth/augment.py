"""From rendered layers to a photograph-like image: compositing and camera effects.

Images are batches (n,H,W,3) uint8 RGB; each step works per image with OpenCV on uint8
(fast, SIMD) or on the whole batch at once with numpy. Geometry never changes here,
so the labels stay exact.
"""
import cv2
import numpy as np


def ambient_occlusion(rgb, depth, alpha, strength):
    """Darken foreground pixels that lie behind their neighbourhood (gaps between
    fingers, the palm under curled fingers): screen-space occlusion from the depth map.

    rgb (n,H,W,3) uint8 (changed in place), depth (n,H,W) metres (0 = none), alpha
    (n,H,W) uint8, strength (n,) darkening at 1 cm of depth below the local average.
    """
    k = max(3, int(round(rgb.shape[1] / 16)) | 1)
    for i in np.flatnonzero(strength > 0):
        m = (alpha[i] > 127).astype(np.float32)
        num = cv2.GaussianBlur(depth[i] * m, (k, k), 0)
        den = cv2.GaussianBlur(m, (k, k), 0)
        occ = np.clip((depth[i] - num / np.maximum(den, 1e-3)) * (100.0 * strength[i]), 0.0, 0.85) * m
        rgb[i] = (rgb[i] * (1.0 - occ)[..., None]).astype(np.uint8)
    return rgb


def contact_shadow(bg, alpha, rng, apply):
    """Darken backgrounds (n,H,W,3) uint8, in place, under a blurred, shifted copy of the
    foreground mask, as if the hand were close to a surface behind it; apply (n,) bool."""
    h, w = bg.shape[1:3]
    for i in np.flatnonzero(apply):
        dx, dy = rng.normal(0, 0.06 * h, 2)
        shift = np.float32([[1, 0, dx], [0, 1, dy]])
        mask = cv2.warpAffine(alpha[i].astype(np.float32) / 255.0, shift, (w, h), borderMode=cv2.BORDER_CONSTANT)
        mask = cv2.GaussianBlur(mask, (0, 0), rng.uniform(0.02, 0.08) * h)
        bg[i] = (bg[i] * (1.0 - rng.uniform(0.25, 0.6) * mask)[..., None]).astype(np.uint8)
    return bg


def composite(fg, alpha, bg):
    """fg over bg where alpha (n,H,W) uint8 > 127 (the renderer's coverage is binary)."""
    return np.where(alpha[..., None] > 127, fg, bg)


def colour_jitter(img, rng):
    """Per image, in place: a 3x3 colour matrix (white-balance gains, saturation,
    brightness), then a tone curve (contrast about mid-grey, gamma) as a lookup table."""
    n = len(img)
    gains = np.exp(rng.normal(0, 0.06, (n, 3))) * np.exp(rng.normal(0, 0.15, (n, 1)))
    sat = rng.uniform(0.6, 1.35, n)
    contrast = rng.uniform(0.75, 1.25, n)
    gamma = np.exp(rng.normal(0, 0.12, n))
    grey = np.full((3, 3), 1.0 / 3.0)
    x = np.arange(256) / 255.0
    for i in range(n):
        M = (sat[i] * np.eye(3) + (1 - sat[i]) * grey) @ np.diag(gains[i])
        cv2.transform(img[i], M, dst=img[i])
        lut = np.clip(0.5 + (x - 0.5) * contrast[i], 0, 1) ** gamma[i]
        img[i] = cv2.LUT(img[i], (lut * 255 + 0.5).astype(np.uint8))
    return img


def motion_kernel(length, angle):
    """(k,k) float32 line kernel of `length` px at `angle` radians, summing to 1."""
    k = int(np.ceil(length)) | 1
    kernel = np.zeros((k, k), np.float32)
    c = k // 2
    dx, dy = np.cos(angle) * (length - 1) / 2, np.sin(angle) * (length - 1) / 2
    cv2.line(kernel, (int(round(c - dx)), int(round(c - dy))), (int(round(c + dx)), int(round(c + dy))), 1.0, 1,
             cv2.LINE_AA)
    return kernel / kernel.sum()


def optics(img, rng, native_scale):
    """Per image, in place: resolution loss (native_scale (n,) = camera pixels per output
    pixel; below 1 the hand was smaller in the real frame than the crop), defocus
    (Gaussian blur, always a little: no lens is perfectly sharp), motion blur.
    Returns (n,) sensor pixels per output pixel (below 1: the image was upsampled from
    fewer pixels), for SensorNoise."""
    n, h, w = img.shape[:3]
    extra_down = np.where(rng.random(n) < 0.25, rng.uniform(1.2, 3.0, n), 1.0)
    scale = np.minimum(native_scale, 1.0) / extra_down
    sigma = np.where(rng.random(n) < 0.25, rng.uniform(0.8, 2.0, n), rng.uniform(0.45, 0.8, n))
    motion = rng.random(n) < 0.2
    for i in range(n):
        x = img[i]
        if scale[i] < 0.95:
            small = (max(8, int(round(w * scale[i]))), max(8, int(round(h * scale[i]))))
            x = cv2.resize(cv2.resize(x, small, interpolation=cv2.INTER_AREA), (w, h), interpolation=cv2.INTER_LINEAR)
        x = cv2.GaussianBlur(x, (0, 0), float(sigma[i]))
        if motion[i]:
            x = cv2.filter2D(x, -1, motion_kernel(rng.uniform(3, 11), rng.uniform(0, np.pi)))
        img[i] = x
    return np.where(scale < 0.95, scale, np.maximum(native_scale, 1.0))


class SensorNoise:
    """Shot (signal-dependent) and read noise drawn from a precomputed bank of Gaussian
    samples (drawing 3M normals per batch would cost more than the rest of the step)."""

    def __init__(self, rng, bank_size=1 << 22):
        self.bank = rng.standard_normal(bank_size, dtype=np.float32)

    def __call__(self, img, rng, sensor_scale=None):
        """img (n,H,W,3) uint8 -> new uint8 array with noise. The noise's standard
        deviation per grey level, sqrt(read^2 + shot^2 * level) DN, is a 256-entry
        table per image, so each pixel costs one lookup and one multiply-add.

        sensor_scale (n,): sensor pixels per output pixel (optics' return). The noise is
        the sensor's, per sensor pixel: an image that was downsampled from k x k sensor
        pixels per output pixel has 1/k of it; one upsampled from fewer pixels has the
        noise of its native pixels, upsampled (smooth, correlated), not fresh per-pixel grain."""
        n, size = len(img), img[0].size
        read = rng.uniform(0.3, 2.5, n).astype(np.float32)                       # DN
        shot = rng.uniform(0.0, 0.25, n).astype(np.float32)                       # DN per sqrt(DN)
        sigma = np.sqrt(read[:, None] ** 2 + shot[:, None] ** 2 * np.arange(256, dtype=np.float32))   # (n,256)
        starts = rng.integers(0, len(self.bank) - size, n)
        mono = rng.random(n) < 0.5                                               # luminance-only noise
        out = np.empty_like(img)
        h, w = img.shape[1:3]
        k = np.ones(n) if sensor_scale is None else np.asarray(sensor_scale, np.float64)
        for i in range(n):
            if k[i] < 0.95:              # upsampled: noise of the native pixels, upsampled
                sh, sw = max(4, int(round(h * k[i]))), max(4, int(round(w * k[i])))
                small = self.bank[starts[i]:starts[i] + sh * sw * 3].reshape(sh, sw, 3)
                noise = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
            else:                        # averaged over k x k sensor pixels
                noise = self.bank[starts[i]:starts[i] + size].reshape(img.shape[1:])
                if k[i] > 1.05:
                    noise = noise * np.float32(1.0 / k[i])
            if mono[i]:
                noise = np.broadcast_to(noise[..., :1], noise.shape)
            x = sigma[i][img[i]]
            x *= noise
            x += img[i]
            x += 0.5
            np.clip(x, 0, 255, out=x)
            out[i] = x
        return out


def jpeg(img, rng, prob=0.6, quality=(25, 95)):
    """Re-encode some uint8 RGB images as JPEG at a random quality (in place)."""
    for i in np.flatnonzero(rng.random(len(img)) < prob):
        ok, buf = cv2.imencode(".jpg", img[i, ..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(*quality))])
        img[i] = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    return img
