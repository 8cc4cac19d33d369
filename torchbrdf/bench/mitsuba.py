"""Mitsuba 3's ``principled`` BSDF on the benchmark's directions and per-lane parameters.

The comparison runs when ``mitsuba``/``drjit`` import (``pip install -e ".[mitsuba]"``); the
LLVM variant ``llvm_ad_rgb`` on the CPU, ``cuda_ad_rgb`` on the GPU. :func:`mitsuba_setup`
builds the BSDF from :func:`torchbrdf.bench.brdf.make_inputs`-style arrays (NumPy, ``[N, C]``),
:func:`mitsuba_fwd` / :func:`mitsuba_fwdbwd` return the timed calls.
"""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["mitsuba_available", "mitsuba_setup", "mitsuba_fwd", "mitsuba_fwdbwd"]


def mitsuba_available(variant: str = "llvm_ad_rgb") -> str | None:
    """Mitsuba version string when ``mitsuba`` with ``variant`` imports, else None."""
    try:
        import mitsuba as mi

        mi.set_variant(variant)
        return mi.__version__
    except Exception:  # noqa: BLE001 - any failure means "not available"
        return None


def mitsuba_setup(inp: dict, variant: str = "llvm_ad_rgb") -> dict:
    """Mitsuba ``principled`` with per-lane parameters.

    Mitsuba's BSDF parameters are textures: each lane reads its own texel of a bitmap with
    nearest filtering (the way per-pixel SVBRDF parameters are fed to Mitsuba). Directions are
    handed over in the local frame (Mitsuba's BSDF interface); ``specular`` is a scalar
    there (it sets the IOR), so it is held at the mean of ours; ``subsurface`` has no
    counterpart.
    """
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    mi.set_variant(variant)
    N = inp["l"].shape[0]
    W = 2048 if N % 2048 == 0 else 1
    H = N // W

    def tex(a):
        return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(a.reshape(H, W, -1), dtype=np.float32)),
                "filter_type": "nearest", "raw": True, "wrap_mode": "clamp"}

    names = {"metallic": "metallic", "roughness": "roughness", "specular_tint": "spec_tint",
             "anisotropic": "anisotropic", "sheen": "sheen", "sheen_tint": "sheen_tint",
             "clearcoat": "clearcoat", "clearcoat_gloss": "clearcoat_gloss"}
    d = {"type": "principled", "base_color": tex(inp["base_color"]),
         "specular": float(inp["specular"].mean())}
    for ours, theirs in names.items():
        d[theirs] = tex(inp[ours])
    bsdf = mi.load_dict(d)
    params = mi.traverse(bsdf)

    def local(w):
        return np.stack([(w * inp[k]).sum(-1) for k in ("x", "y", "n")]).astype(np.float32)

    def vec(a):
        return mi.Vector3f(np.ascontiguousarray(a.T, dtype=np.float32))

    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    uv = mi.Point2f(np.stack([(jj.ravel() + 0.5) / W, (ii.ravel() + 0.5) / H]).astype(np.float32))
    wi, wo = mi.Vector3f(local(inp["v"])), mi.Vector3f(local(inp["l"]))
    world = {k: vec(inp[k]) for k in ("l", "v", "n", "x", "y")}
    dr.eval(uv, wi, wo, *world.values())
    keys = [k for k in params.keys() if k.endswith(".data")]
    return dict(bsdf=bsdf, params=params, keys=keys, uv=uv, wi=wi, wo=wo, world=world, N=N, ctx=mi.BSDFContext())


def _evaluate(s, world: bool, grad: bool):
    """One evaluation; ``world``: from the same world-space l, v, n, x, y as torchbrdf (the frame
    change to Mitsuba's local coordinates is part of the timed call), else from local directions."""
    import drjit as dr
    import mitsuba as mi

    if world:
        w = {k: mi.Vector3f(t) for k, t in s["world"].items()} if grad else s["world"]
        if grad:
            for t in w.values():
                dr.enable_grad(t)
        frame = mi.Frame3f(w["x"], w["y"], w["n"])
        wi, wo = frame.to_local(w["v"]), frame.to_local(w["l"])
        leaves = list(w.values())
    else:
        wi, wo = (mi.Vector3f(s["wi"]), mi.Vector3f(s["wo"])) if grad else (s["wi"], s["wo"])
        if grad:
            dr.enable_grad(wi)
            dr.enable_grad(wo)
        leaves = [wi, wo]
    return s["bsdf"].eval(s["ctx"], _surface_interaction(s, wi), wo), leaves


def _surface_interaction(s, wi):
    import drjit as dr
    import mitsuba as mi

    si = dr.zeros(mi.SurfaceInteraction3f, s["N"])
    si.wi = wi
    si.uv = s["uv"]
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    return si


def mitsuba_fwd(s: dict, world: bool = True) -> Callable[[], None]:
    """The timed forward call on :func:`mitsuba_setup`'s ``s`` (``world``: from world-space directions)."""
    import drjit as dr

    def run():
        val, _ = _evaluate(s, world, grad=False)
        dr.eval(val)
        dr.sync_thread()
    return run


def mitsuba_fwdbwd(s: dict, world: bool = True) -> Callable[[], None]:
    """The timed forward+backward call (gradients of every parameter texture and direction)."""
    import drjit as dr

    def run():
        params = s["params"]
        for k in s["keys"]:
            dr.enable_grad(params[k])
        params.update()
        val, leaves = _evaluate(s, world, grad=True)
        dr.backward_from(val)
        grads = [dr.grad(params[k]) for k in s["keys"]] + [dr.grad(t) for t in leaves]
        dr.eval(*grads)
        dr.sync_thread()
        for k in s["keys"]:
            dr.disable_grad(params[k])
    return run

