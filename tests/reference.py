"""Independent float64 NumPy reference of the principled BRDF, written from the equations of
the "principled BRDF core" issue (Burley 2012 + 2014 addendum). It shares no code with
torchbrdf: it always uses the anisotropic forms with an explicit frame and the naive
``1 + (α² - 1) cos²`` clearcoat denominator (harmless in float64 away from α = 1).
"""

import numpy as np

DEFAULTS = dict(
    metallic=0.0, subsurface=0.0, specular=0.5, roughness=0.5, specular_tint=0.0,
    anisotropic=0.0, sheen=0.0, sheen_tint=0.5, clearcoat=0.0, clearcoat_gloss=1.0,
)


def _d(a, b):
    return np.sum(a * b, axis=-1, keepdims=True)


def _s(u):
    return (1.0 - np.clip(u, 0.0, 1.0)) ** 5


def _lerp(a, b, t):
    return a + (b - a) * t


def principled_ref(l, v, n, x, y, base_color, **params):
    """f(l, v) ``(N, 3)`` for arrays ``(N, 3)`` and parameters ``(N, 1)`` or floats."""
    p = {**DEFAULTS, **params}
    nl, nv = _d(n, l), _d(n, v)
    h = l + v
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    nh, lh = _d(n, h), _d(l, h)
    lum = 0.3 * base_color[..., :1] + 0.6 * base_color[..., 1:2] + 0.1 * base_color[..., 2:]
    ctint = np.where(lum > 0, base_color / np.where(lum > 0, lum, 1.0), 1.0)
    cspec0 = _lerp(0.08 * p["specular"] * _lerp(1.0, ctint, p["specular_tint"]), base_color, p["metallic"])
    csheen = _lerp(1.0, ctint, p["sheen_tint"])
    fl, fv = _s(nl), _s(nv)
    r = p["roughness"]
    fd90 = 0.5 + 2 * r * lh ** 2
    fd = _lerp(1.0, fd90, fl) * _lerp(1.0, fd90, fv)
    fss90 = r * lh ** 2
    fss = _lerp(1.0, fss90, fl) * _lerp(1.0, fss90, fv)
    ss = 1.25 * (fss * (1.0 / (nl + nv) - 0.5) + 0.5)
    aspect = np.sqrt(1 - 0.9 * np.asarray(p["anisotropic"]))
    ax = np.maximum(0.001, r ** 2 / aspect)
    ay = np.maximum(0.001, r ** 2 * aspect)
    ds = 1.0 / (np.pi * ax * ay * ((_d(h, x) / ax) ** 2 + (_d(h, y) / ay) ** 2 + nh ** 2) ** 2)
    fh = _s(lh)
    fs = _lerp(cspec0, 1.0, fh)

    def g(w):
        return 1.0 / (_d(n, w) + np.sqrt((_d(w, x) * ax) ** 2 + (_d(w, y) * ay) ** 2 + _d(n, w) ** 2))

    gs = g(l) * g(v)
    fsheen = fh * p["sheen"] * csheen
    ac = _lerp(0.1, 0.001, p["clearcoat_gloss"])
    dr = (ac ** 2 - 1) / (np.pi * np.log(ac ** 2) * (1 + (ac ** 2 - 1) * nh ** 2))
    fr = _lerp(0.04, 1.0, fh)

    def gc(w):
        c = _d(n, w)
        return 1.0 / (c + np.sqrt(0.0625 + c ** 2 - 0.0625 * c ** 2))

    gr = gc(l) * gc(v)
    f = ((1 / np.pi) * _lerp(fd, ss, p["subsurface"]) * base_color + fsheen) * (1 - p["metallic"])
    f = f + gs * fs * ds + 0.25 * p["clearcoat"] * gr * fr * dr
    return np.where((nl > 0) & (nv > 0), f, 0.0)
