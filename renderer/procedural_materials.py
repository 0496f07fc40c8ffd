"""Colours, textures, materials and the sky of the procedural generator (renderer/procedural.py): plain dicts,
with numpy arrays where Mitsuba needs objects (converted when the plan is loaded).
"""

from __future__ import annotations

import numpy as np

from gradsep.model.policy import LUMINANCE
from gradsep.renderer.procedural_geometry import Vec


def _rgb(value: Vec) -> dict:
    return {"type": "rgb", "value": [float(x) for x in value]}


def _hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    k = (np.array([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    return v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def _light_tint(rng: np.random.Generator) -> np.ndarray:
    """Mostly white-ish light with a warm or cool cast; luminance normalised to 1 so power stays as drawn."""
    warm = np.array([1.0, 0.78, 0.52])
    cool = np.array([0.72, 0.85, 1.0])
    t = rng.uniform(-1.0, 1.0)
    tint = 1.0 + max(t, 0.0) * (warm - 1.0) + max(-t, 0.0) * (cool - 1.0)
    if rng.random() < 0.1:  # an occasional saturated coloured light
        tint = 0.3 + 0.7 * _hsv_to_rgb(rng.random(), rng.uniform(0.4, 0.8), 1.0)
    return tint / float(tint @ np.array(LUMINANCE))


def _albedo(rng: np.random.Generator, lo: float = 0.05, hi: float = 0.9) -> np.ndarray:
    """A random surface colour: varied hue and saturation, brightness kept physically plausible (< 0.9)."""
    h, s = rng.random(), rng.uniform(0.0, 0.85) ** 1.5
    return np.clip(_hsv_to_rgb(h, s, rng.uniform(lo, hi)), 0.01, 0.95)


def _noise(rng: np.random.Generator, size: int = 64, cells: int | None = None) -> np.ndarray:
    """Smooth value noise in [0, 1] of shape (size, size): a few octaves of bilinearly upsampled random grids."""
    from scipy.ndimage import zoom

    out = np.zeros((size, size))
    amp, total = 1.0, 0.0
    cells = cells or int(rng.integers(3, 9))
    while cells <= size // 2:
        grid = rng.random((cells, cells))
        out += amp * zoom(grid, size / cells, order=1, mode="grid-wrap", grid_mode=True)[:size, :size]
        total += amp
        amp *= 0.5
        cells *= 2
    out /= total
    return (out - out.min()) / max(float(np.ptp(out)), 1e-6)


def _texture(rng: np.random.Generator, base: np.ndarray) -> dict:
    """A checkerboard (Mitsuba plugin) or a procedural noise/stripe bitmap around colour ``base``."""
    other = _albedo(rng)
    scale = float(rng.choice([2.0, 4.0, 6.0, 8.0, 12.0]))
    to_uv = np.diag([scale, scale, 1.0])
    if rng.random() < 0.6:
        return {"type": "checkerboard", "color0": _rgb(base), "color1": _rgb(other), "to_uv": to_uv}
    n = _noise(rng)
    if rng.random() < 0.4:  # stripes warped by the noise: wood-grain-like high frequencies
        x = np.linspace(0.0, 1.0, n.shape[1], endpoint=False)[None, :]
        n = 0.5 + 0.5 * np.sin(2 * np.pi * (rng.integers(3, 10) * x + 2.0 * n))
    image = (base[None, None, :] * (1 - n[..., None]) + other[None, None, :] * n[..., None]).astype(np.float32)
    return {"type": "bitmap", "bitmap": image, "filter_type": "bilinear", "wrap_mode": "repeat",
            "to_uv": np.diag([scale / 4, scale / 4, 1.0])}


def _reflectance(rng: np.random.Generator, textured_p: float, lo: float = 0.05, hi: float = 0.9) -> tuple:
    base = _albedo(rng, lo, hi)
    if rng.random() < textured_p:
        tex = _texture(rng, base)
        return tex, f"textured-{tex['type']}"
    return _rgb(base), "plain"


_CONDUCTORS = ("Au", "Ag", "Al", "Cu", "Cr", "W", "Rh", "Ni_palik")  # names Mitsuba ships data for


def _material(rng: np.random.Generator, closed: bool) -> tuple[dict, str]:
    """A random object material and its category name. ``closed``: the shape encloses a volume (dielectrics)."""
    kinds = ["diffuse", "plastic", "roughplastic", "conductor", "roughconductor", "dielectric", "roughdielectric"]
    weights = np.array([0.36, 0.07, 0.10, 0.09, 0.16, 0.12, 0.10])
    kind = str(rng.choice(kinds, p=weights / weights.sum()))
    if kind == "diffuse":
        refl, tex = _reflectance(rng, 0.35)
        return {"type": "diffuse", "reflectance": refl}, "diffuse" + ("" if tex == "plain" else "-textured")
    if kind in ("plastic", "roughplastic"):
        refl, tex = _reflectance(rng, 0.25)
        bsdf = {"type": kind, "diffuse_reflectance": refl, "int_ior": float(rng.uniform(1.4, 1.7))}
        if kind == "roughplastic":
            bsdf["alpha"] = float(rng.uniform(0.05, 0.4))
        return bsdf, kind
    if kind in ("conductor", "roughconductor"):
        if rng.random() < 0.6:
            bsdf: dict = {"type": kind, "material": str(rng.choice(_CONDUCTORS))}
        else:  # an idealised tinted mirror
            bsdf = {"type": kind, "material": "none",
                    "specular_reflectance": _rgb(np.clip(_albedo(rng, 0.5, 0.95), 0.3, 0.95))}
        if kind == "roughconductor":
            bsdf["alpha"] = float(rng.uniform(0.03, 0.5))
            bsdf["distribution"] = str(rng.choice(["ggx", "beckmann"]))
        return bsdf, kind
    ior = float(rng.uniform(1.3, 1.8))
    if not closed:  # a sheet has no inside: a thin dielectric (window-like pane) is the consistent model
        return {"type": "thindielectric", "int_ior": ior}, "thindielectric"
    bsdf = {"type": kind, "int_ior": ior}
    if kind == "roughdielectric":
        bsdf["alpha"] = float(rng.uniform(0.03, 0.35))
    if rng.random() < 0.3:  # tinted glass
        bsdf["specular_transmittance"] = _rgb(np.clip(_albedo(rng, 0.6, 1.0), 0.4, 1.0))
    return bsdf, kind


def _twosided(bsdf: dict) -> dict:
    return {"type": "twosided", "bsdf": bsdf}


def _sky(rng: np.random.Generator, width: int = 128) -> tuple[np.ndarray, dict]:
    """A small equirectangular sky: zenith-to-horizon gradient, a ground colour, soft clouds and a sun."""
    h = width // 2
    theta = (np.arange(h) + 0.5) / h * np.pi               # 0 at the zenith (+y)
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi
    elev = (np.pi / 2 - theta)[:, None] * np.ones((1, width))
    zenith = np.array([0.25, 0.45, 1.0]) * rng.uniform(0.5, 1.5)
    horizon = np.array([1.0, 0.9, 0.8]) * rng.uniform(0.6, 1.6)
    ground = _albedo(rng, 0.1, 0.5) * rng.uniform(0.2, 0.6)
    t = np.clip(elev / (np.pi / 2), 0.0, 1.0)[..., None] ** 0.5
    img = np.where(elev[..., None] > 0, horizon * (1 - t) + zenith * t, ground)
    clouds = _noise(rng, size=width)[:h, :]
    cover = rng.uniform(0.0, 0.8)
    mask = np.clip((clouds - (1 - cover)) * 4.0, 0.0, 1.0)[..., None] * (elev[..., None] > 0)
    img = img * (1 - mask) + mask * np.array([1.0, 1.0, 1.0]) * rng.uniform(0.8, 1.4)
    sun_el = rng.uniform(np.radians(8), np.radians(65))
    sun_az = rng.uniform(0, 2 * np.pi)
    sun_power = 0.0
    if rng.random() < 0.7:
        sun_dir = np.array([np.cos(sun_el) * np.cos(sun_az), np.sin(sun_el), np.cos(sun_el) * np.sin(sun_az)])
        dirs = np.stack([np.sin(theta)[:, None] * np.cos(phi)[None, :],
                         np.cos(theta)[:, None] * np.ones((1, width)),
                         np.sin(theta)[:, None] * np.sin(phi)[None, :]], axis=-1)
        ang = np.arccos(np.clip(dirs @ sun_dir, -1.0, 1.0))
        sun_power = float(rng.uniform(30.0, 300.0))
        img = img + (sun_power * np.exp(-0.5 * (ang / np.radians(2.5)) ** 2))[..., None] * np.array(
            [1.0, 0.9, 0.75])
    info = {"sun": sun_power > 0, "cloud_cover": round(float(cover), 3)}
    return img.astype(np.float32), info

