"""Random appearance: skin tones, nails, sleeves, lights — the shader's parameter blocks.

Colours are sampled in sRGB (what photographs show) and handed to the shader in linear
light (sRGB^2.2). `material_blocks` builds the shader's mat[7] vec4 block per hand,
`light_blocks` its light[7] block per tile (see atlas.py for the layout).
"""
import numpy as np

# sRGB albedos of skin as photographs show it, light to dark (dorsal side), spanning the
# ten Monk skin tones but with the redness and saturation that real skin under room light has
SKIN_TONES = np.array([
    (238, 200, 182), (230, 186, 163), (221, 172, 145), (204, 153, 120), (184, 132, 98),
    (158, 108, 76), (128, 84, 58), (102, 66, 47), (78, 52, 38), (58, 40, 31),
], dtype=np.float64) / 255.0
PALM_TONE = np.array([226, 170, 150]) / 255.0        # palms are lighter and pinker, most on dark skin
NAIL_TONE = np.array([236, 204, 198]) / 255.0


def to_linear(srgb):
    return np.clip(srgb, 0.0, 1.0) ** 2.2


def kelvin_to_rgb(kelvin):
    """(...,) colour temperature in K -> (..., 3) linear RGB with unit luminance
    (Tanner Helland's fit of the black-body locus, 1000-40000 K)."""
    t = np.asarray(kelvin, dtype=np.float64) / 100.0
    r = np.where(t <= 66, 255.0, 329.698727446 * np.maximum(t - 60, 1e-6) ** -0.1332047592)
    g = np.where(t <= 66, 99.4708025861 * np.log(t) - 161.1195681661,
                 288.1221695283 * np.maximum(t - 60, 1e-6) ** -0.0755148492)
    b = np.where(t >= 66, 255.0, np.where(t <= 19, 0.0, 138.5177312231 * np.log(np.maximum(t - 10, 1e-6))
                                          - 305.0447927307))
    rgb = to_linear(np.stack([r, g, b], -1) / 255.0)
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
    return rgb / lum[..., None]


def random_hsv_colours(rng, n, sat=(0.0, 0.9), val=(0.1, 0.95)):
    """(n,3) sRGB colours from uniform hue, given saturation and value ranges."""
    h = rng.random(n) * 6.0
    s = rng.uniform(*sat, n)
    v = rng.uniform(*val, n)
    k = lambda m: (m + h) % 6
    f = lambda m: v - v * s * np.clip(np.minimum(k(m), 4 - k(m)), 0, 1)
    return np.stack([f(5), f(3), f(1)], -1)


def sample_skin(rng, n):
    """Per hand: dorsal, palm, nail albedos (sRGB, (n,3) each) and darkness (n,) in [0,1]."""
    t = rng.random(n) * (len(SKIN_TONES) - 1)
    i = np.minimum(t.astype(int), len(SKIN_TONES) - 2)
    f = (t - i)[:, None]
    base = SKIN_TONES[i] * (1 - f) + SKIN_TONES[i + 1] * f
    # individual variation: redness / yellowness and overall lightness
    base = base * (1 + rng.normal(0, 0.04, (n, 1))) + rng.normal(0, 0.02, (n, 1)) * np.array([1.0, -0.3, -0.8])
    base = np.clip(base, 0.05, 1.0)
    darkness = t / (len(SKIN_TONES) - 1)
    palm = base + (PALM_TONE - base) * (0.15 + 0.55 * darkness)[:, None]
    nail = base + (NAIL_TONE - base) * (0.45 + 0.35 * darkness)[:, None]
    polish = rng.random(n) < 0.06
    nail[polish] = random_hsv_colours(rng, int(polish.sum()), sat=(0.5, 0.9), val=(0.3, 0.9))
    return base, palm, nail, darkness


def material_blocks(rng, base, palm, nail, darkness, ids, sleeve_prob=0.6):
    """(n,7,4) float32 shader material blocks for skin (one per hand)."""
    n = len(base)
    mat = np.zeros((n, 7, 4), np.float32)
    mat[:, 0, :3] = to_linear(base)
    mat[:, 0, 3] = ids
    mat[:, 1, :3] = to_linear(palm)
    mat[:, 1, 3] = rng.uniform(0.08, 0.35, n)                        # specular strength
    mat[:, 2, :3] = to_linear(nail)
    mat[:, 2, 3] = rng.uniform(8, 30, n)                             # shininess
    sleeve = rng.random(n) < sleeve_prob
    mat[:, 3, :3] = to_linear(random_hsv_colours(rng, n, sat=(0.0, 0.8), val=(0.05, 0.9)))
    mat[:, 3, 3] = np.where(sleeve, rng.uniform(0.05, 0.30, n), 10.0)  # rest-y where the sleeve starts
    mat[:, 4, :3] = np.array([0.88, 0.78, 0.78]) - 0.08 * darkness[:, None]   # knuckles darker, redder
    mat[:, 4, 3] = rng.uniform(0.06, 0.22, n)                        # albedo noise amplitude
    mat[:, 6, 3] = rng.uniform(0.5, 1.0, n)                          # subsurface tint strength
    return mat


def object_blocks(rng, n, ids):
    """(n,7,4) float32 shader material blocks for occluding objects."""
    mat = np.zeros((n, 7, 4), np.float32)
    mat[:, 0, :3] = to_linear(random_hsv_colours(rng, n))
    mat[:, 0, 3] = ids
    mat[:, 1, 3] = rng.uniform(0.0, 0.6, n)
    mat[:, 2, 3] = rng.uniform(5, 80, n)
    mat[:, 5, 0] = 1.0
    mat[:, 5, 1] = rng.integers(0, 4, n)                             # none, stripes, checker, blotches
    mat[:, 5, 2] = rng.uniform(40, 300, n)                           # pattern frequency, 1/m
    mat[:, 5, 3] = rng.uniform(0.3, 1.0, n)
    mat[:, 6, :3] = to_linear(random_hsv_colours(rng, n))
    return mat


def light_blocks(rng, n, ambient_rgb=None):
    """(n,7,4) float32 per-tile light blocks (camera frame directions).

    ambient_rgb: optional (n,3) linear colour of the surroundings (e.g. the background's
    mean), mixed into the sky and ground colours so hand and scene agree.
    """
    light = np.zeros((n, 7, 4), np.float32)
    # key light: from the camera's side of the hand mostly (-z), often from above (-y)
    key = rng.normal(size=(n, 3)) + np.array([0.0, -0.6, -1.2])
    key /= np.linalg.norm(key, axis=1, keepdims=True)
    fill = -key + rng.normal(0, 0.6, (n, 3)) + np.array([0.0, 0.0, -0.8])
    fill /= np.linalg.norm(fill, axis=1, keepdims=True)
    key_t = rng.uniform(2700, 7500, n)
    fill_t = np.clip(key_t + rng.normal(0, 1500, n), 2500, 9000)
    light[:, 0, :3], light[:, 0, 3] = key, rng.uniform(0.5, 1.3, n)
    light[:, 1, :3], light[:, 1, 3] = kelvin_to_rgb(key_t), rng.uniform(0.15, 0.5, n)
    light[:, 2, :3], light[:, 2, 3] = fill, rng.uniform(0.05, 0.45, n)
    light[:, 3, :3], light[:, 3, 3] = kelvin_to_rgb(fill_t), rng.uniform(0.85, 1.25, n)
    sky = kelvin_to_rgb(rng.uniform(4000, 9000, n))
    ground = kelvin_to_rgb(rng.uniform(2700, 6000, n)) * rng.uniform(0.4, 0.9, (n, 1))
    if ambient_rgb is not None:
        env = np.asarray(ambient_rgb) / np.maximum(np.asarray(ambient_rgb) @ np.array([0.2126, 0.7152, 0.0722]),
                                                   0.05)[:, None]
        w = rng.uniform(0.2, 0.6, (n, 1))
        sky, ground = sky * (1 - w) + env * w, ground * (1 - w) + env * w * 0.7
    light[:, 4, :3], light[:, 4, 3] = sky, rng.uniform(0.15, 0.45, n)
    light[:, 5, :3], light[:, 5, 3] = ground, rng.uniform(0.5, 1.2, n)
    up = np.array([0.0, -1.0, 0.0]) + rng.normal(0, 0.25, (n, 3))
    light[:, 6, :3] = up / np.linalg.norm(up, axis=1, keepdims=True)
    return light
