"""Fused CPU kernels for :func:`torchbrdf.principled`: one pass forward, one pass backward.

Why: the eager path launches ~150 ATen kernels per call and autograd keeps dozens of
``(N, 1)`` intermediates alive (several GiB at N = 2^22). Here the whole per-lane formula
is one C loop (OpenMP over lanes, auto-vectorised by gcc), the backward recomputes the
forward inside the same loop and writes each input's gradient directly, so the evaluation
holds no intermediate tensors at all: memory = inputs + gradients + output.

How: the formula is written once (:func:`_build_principled`) in a tiny tracing language
(:class:`_Node`) that mirrors ``_principled_eager`` operation by operation, with the same
rounding (float32 arithmetic, the half-vector projections and ``1 - l·h`` in float64, Python
floats folded in double exactly as eager Python does). From the traced graph we emit C for
the forward and, by reverse-mode differentiation of the graph, for the backward (the
adjoint rules are those of ATen's autograd formulas: ``clamp`` passes the gradient where
the input is inside the bounds, ``where`` routes it to the selected branch, ...).

Compilation: ``gcc -O3 -march=native -fopenmp -ffp-contract=off`` (no ``-ffast-math``: the
kernels keep IEEE semantics so values match eager), once per *kernel family* — dtype,
which parameters are tensors vs Python floats (floats are runtime arguments, so sweeping a
float parameter does not recompile), active lobes, tint/frame use, broadcast pattern and,
for the backward, which inputs need gradients. :mod:`torchbrdf.kernels.build` caches the shared
library per user (``$TORCHBRDF_CACHE_DIR/kernels``, default ``~/.cache/torchbrdf/kernels``), so
the ~1–3 s build is paid once per machine and family; loading a cached kernel takes
milliseconds. No compiler, or any build/cache failure → eager (one warning). The OpenMP loops
run on PyTorch's own OpenMP runtime and thread count (see ``build``).

Limits: CPU float32/float64 only (CUDA and others use eager), first-order gradients (a
``create_graph=True`` backward re-runs the eager path to build a differentiable graph),
no forward-mode AD / vmap / torch.compile tracing through it (dispatch sends those to eager).
"""

from __future__ import annotations

import ctypes
import math
import mmap
import os
import threading
import weakref

import torch
from torch import Tensor

from torchbrdf.kernels import build as _build

__all__ = ["available", "principled_fast", "kernel_cache_dir", "compiled_kernels", "empty_cache"]

INV_PI = 1.0 / math.pi
COS_EPS = 1e-7
ASPECT2_MIN = 0.1
ALPHA_MIN = 1e-3
SQRT_EPS = 1e-12
NORM_EPS = 1e-12
_SERIES_EPS = 1e-4

VEC_NAMES = ("l", "v", "n", "x", "y")
SCALAR_NAMES = ("metallic", "subsurface", "specular", "roughness", "specular_tint", "anisotropic",
                "sheen", "sheen_tint", "clearcoat", "clearcoat_gloss")


# ---------------------------------------------------------------------------------------------
# The tracing language
# ---------------------------------------------------------------------------------------------
# Node kinds: 'r' = a tensor in the compute dtype (float or double), 'd' = a float64 tensor
# (the half-vector terms of float32 inputs), 'p' = a runtime Python float (double, uniform over
# lanes), 'b' = a boolean mask. Python numbers stay Python numbers and fold in double, exactly
# as in the eager code.

class _Graph:
    def __init__(self):
        self.nodes: list[_Node] = []


_G: _Graph | None = None


class _Node:
    __slots__ = ("id", "op", "args", "kind", "attr", "grad")

    def __init__(self, op, args, kind, attr=None):
        self.op, self.args, self.kind, self.attr = op, tuple(args), kind, attr
        self.grad = op == "in" or (op != "stopgrad" and any(isinstance(a, _Node) and a.grad for a in self.args))
        self.id = len(_G.nodes)
        _G.nodes.append(self)

    # arithmetic -------------------------------------------------------------------------
    def __add__(self, o):
        return _bin("add", self, o)

    def __radd__(self, o):
        return _bin("add", o, self)

    def __sub__(self, o):
        return _bin("sub", self, o)

    def __rsub__(self, o):
        return _bin("sub", o, self)

    def __mul__(self, o):
        return _bin("mul", self, o)

    def __rmul__(self, o):
        return _bin("mul", o, self)

    def __truediv__(self, o):
        return _div(self, o)

    def __rtruediv__(self, o):
        return _div(o, self)

    def __neg__(self):
        return _Node("neg", (self,), self.kind)

    def __gt__(self, o):
        return _cmp("gt", self, o)

    def __lt__(self, o):
        return _cmp("lt", self, o)

    def __and__(self, o):
        return _Node("and", (self, o), "b")


def _is_tensor(a) -> bool:
    return isinstance(a, _Node) and a.kind in ("r", "d")


def _kind(a) -> str:
    return a.kind if isinstance(a, _Node) else "c"


def _to_kind(a, kind):
    if not isinstance(a, _Node):
        return _Node("const", (), kind, float(a))
    if a.kind == kind or (a.kind == "p" and kind == "d"):
        return a
    if a.kind == "p" and kind == "r":
        return _Node("tor", (a,), "r")
    raise TypeError(f"implicit mix of {a.kind} and {kind}")


def _target(*xs) -> str:
    ks = {_kind(x) for x in xs}
    for k in ("r", "d", "p"):
        if k in ks:
            return k
    return "c"


def _bin(op, a, b):
    t = _target(a, b)
    if t == "c":
        return {"add": a + b, "sub": a - b, "mul": a * b}[op]
    return _Node(op, (_to_kind(a, t), _to_kind(b, t)), t)


def _div(a, b):
    if _target(a, b) == "c":
        return a / b
    if _is_tensor(b) and not _is_tensor(a):
        # torch: ``number / tensor`` is ``tensor.reciprocal() * number``.
        return _bin("mul", _Node("recip", (b,), b.kind), a)
    return _bin("div", a, b)


def _cmp(op, a, b):
    t = _target(a, b)
    return _Node(op, (_to_kind(a, t), _to_kind(b, t)), "b")


def _un(op, a):
    return _Node(op, (a,), a.kind)


def sqrt(a):
    return math.sqrt(a) if not isinstance(a, _Node) else _un("sqrt", a)


def rsqrt(a):
    return _un("rsqrt", a)


def log(a):
    return _un("log", a)


def log1p(a):
    return _un("log1p", a)


def absv(a):
    return _un("abs", a)


def clamp_min(a, lo):
    """``torch.clamp(a, min=lo)`` on a tensor, Python ``max`` on numbers."""
    if _is_tensor(a):
        return _Node("maxc", (a, _to_kind(lo, a.kind)), a.kind)
    if isinstance(a, _Node):  # runtime Python float: max(a, lo)
        return _Node("pmax", (a, _to_kind(lo, "p")), "p")
    return max(a, lo)


def clamp(a, lo, hi):
    return _Node("clamp", (a, _to_kind(lo, a.kind), _to_kind(hi, a.kind)), a.kind)


def where(c, a, b):
    t = _target(a, b)
    t = "r" if t == "c" else t
    return _Node("where", (c, _to_kind(a, t), _to_kind(b, t)), t)


def tod(a):
    return _Node("tod", (a,), "d")


def tor(a):
    return _Node("tor", (a,), "r")


def as_tensor(a):
    """``torch.as_tensor(a, dtype=compute dtype)``: numbers and runtime floats become 'r'."""
    return a if _is_tensor(a) else _to_kind(a, "r")


def _dot(a, b):
    return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]


def _cross_norm2(a, b):
    c0 = a[1] * b[2] - a[2] * b[1]
    c1 = a[2] * b[0] - a[0] * b[2]
    c2 = a[0] * b[1] - a[1] * b[0]
    return (c0 * c0 + c1 * c1) + c2 * c2


def _lerp(a, b, t):
    return a + (b - a) * t


def _pow5(m):
    m2 = m * m
    return m2 * m2 * m


def _schlick_weight(u):
    return _pow5(clamp(1.0 - u, 0.0, 1.0))


def _g_over_4nn(nw, ta2):
    return 1.0 / (nw + sqrt(clamp_min(nw * nw + ta2, SQRT_EPS)))


def _build_principled(inp: dict, active: tuple, need_tint: bool, frame: bool, hi_double: bool):
    """Trace the principled BRDF; mirrors ``principled._principled_eager`` step by step.

    ``inp`` maps names to 3-tuples of nodes (vectors, colours), nodes or numbers (scalars).
    Returns the three output channel nodes.
    """
    l, v, n = inp["l"], inp["v"], inp["n"]
    base = inp["base_color"]
    metallic, roughness = inp["metallic"], inp["roughness"]

    nl_raw, nv_raw = _dot(n, l), _dot(n, v)
    valid = (nl_raw > 0.0) & (nv_raw > 0.0)
    nl = clamp_min(nl_raw, COS_EPS)
    nv = clamp_min(nv_raw, COS_EPS)

    # half_vector_terms: in float64 for float32 inputs, rounded once.
    up = tod if hi_double else (lambda t: t)
    down = tor if hi_double else (lambda t: t)
    lw, vw, nw = [up(c) for c in l], [up(c) for c in v], [up(c) for c in n]
    s = [a + b for a, b in zip(lw, vw)]
    ssq = clamp_min(_dot(s, s), NORM_EPS)
    r = rsqrt(ssq)
    h = [c * r for c in s]
    lh_w = clamp(_dot(lw, h), 0.0, 1.0)
    terms = {"nh": _dot(nw, h), "lh": lh_w, "one_minus_lh": 1.0 - lh_w, "sin2_h": _cross_norm2(nw, h)}
    x = y = None
    if frame:
        x, y = inp["x"], inp["y"]
        terms["hx"] = _dot(h, [up(c) for c in x])
        terms["hy"] = _dot(h, [up(c) for c in y])
    hg = {k: down(t) for k, t in terms.items()}
    nh, lh = hg["nh"], hg["lh"]
    fh = _pow5(hg["one_minus_lh"])

    if need_tint:
        lum = 0.3 * base[0] + 0.6 * base[1] + 0.1 * base[2]
        positive = lum > 0.0
        ctint = [where(positive, b / where(positive, lum, 1.0), 1.0) for b in base]
    else:
        ctint = [1.0, 1.0, 1.0]

    f = [None, None, None]

    def acc(c, term):
        f[c] = term if f[c] is None else f[c] + term

    dielectric = 1.0 - metallic

    if "diffuse" in active or "subsurface" in active:
        ss_w = inp["subsurface"]
        mix = 0.0
        if "diffuse" in active:
            fd90 = 0.5 + 2.0 * roughness * lh * lh
            fd = _lerp(1.0, fd90, _schlick_weight(nl)) * _lerp(1.0, fd90, _schlick_weight(nv))
            mix = fd * (1.0 - ss_w)
        if "subsurface" in active:
            fss90 = roughness * lh * lh
            fss = _lerp(1.0, fss90, _schlick_weight(nl)) * _lerp(1.0, fss90, _schlick_weight(nv))
            inv = 1.0 / clamp_min(nl + nv, 1e-7)
            ss = 1.25 * (fss * (inv - 0.5) + 0.5)
            mix = mix + ss * ss_w
        w = INV_PI * mix
        for c in range(3):
            acc(c, w * base[c] * dielectric)

    if "sheen" in active:
        sh = fh * inp["sheen"]
        for c in range(3):
            acc(c, sh * _lerp(1.0, ctint[c], inp["sheen_tint"]) * dielectric)

    if "specular" in active:
        dg = _specular_dg(inp, l, v, nl, nv, hg, roughness, frame, x, y)
        for c in range(3):
            cspec0 = _lerp(0.08 * inp["specular"] * _lerp(1.0, ctint[c], inp["specular_tint"]), base[c], metallic)
            fs = _lerp(cspec0, 1.0, fh)
            acc(c, fs * dg)

    if "clearcoat" in active:
        alpha_c = _lerp(0.1, 0.001, inp["clearcoat_gloss"])
        alpha_c = clamp_min(alpha_c, ALPHA_MIN)
        # ndf_gtr1(nh, alpha_c, sin2_h)
        alpha_t = as_tensor(alpha_c)
        a2 = alpha_t * alpha_t
        base_d = a2 * nh * nh + hg["sin2_h"]
        # Eager: log_a2 = where(0.5 < a2 < 2, log1p(a2 - 1), log(a2)); log_t = where(small,
        # log1p(ts), log_a2). Here one log per lane gives the same selected values: for
        # 0.5 < a2 < 2, a2 - 1 and 1 + (a2 - 1) are exact, so log1p(a2 - 1) (Goldberg's form,
        # as tb_log1p computes it) *is* log(a2); and where `small`, the exact branch is
        # discarded, so its denominator only needs to stay finite and non-zero.
        log_a2 = log(a2)
        t = a2 - 1.0
        small = absv(t) < _SERIES_EPS
        ts = where(small, 1.0, t)
        log_t = where(small, 1.0, log_a2)
        exact = ts / log_t
        series = 1.0 + t * (0.5 + t * (-1.0 / 12.0 + t / 24.0))
        d = where(small, series, exact) / (math.pi * base_d)
        dr = where(nh > 0.0, d, 0.0)
        fr = _lerp(0.04, 1.0, fh)
        gr = _g_over_4nn(nl, 0.0625 * (1.0 - nl * nl)) * _g_over_4nn(nv, 0.0625 * (1.0 - nv * nv))
        cc = 0.25 * inp["clearcoat"] * gr * fr * dr
        for c in range(3):
            acc(c, cc)

    out = []
    for c in range(3):
        fc = f[c] if f[c] is not None else 0.0
        out.append(where(valid, fc, 0.0))
    return out


def _specular_dg(inp, l, v, nl, nv, hg, roughness, frame, x, y):
    aniso = inp["anisotropic"]
    nh = hg["nh"]
    r2 = roughness * roughness
    if not frame:
        alpha = clamp_min(r2, ALPHA_MIN)
        a2 = alpha * alpha
        den = a2 * nh * nh + hg["sin2_h"]
        ds = a2 / (math.pi * den * den)
        gs = _g_over_4nn(nl, a2 * (1.0 - nl * nl)) * _g_over_4nn(nv, a2 * (1.0 - nv * nv))
        return where(nh > 0.0, ds * gs, 0.0)
    aspect2 = 1.0 - 0.9 * aniso
    aspect = sqrt(clamp_min(aspect2, ASPECT2_MIN))
    ax = clamp_min(r2 / aspect, ALPHA_MIN)
    ay = clamp_min(r2 * aspect, ALPHA_MIN)
    hx, hy = hg["hx"] / ax, hg["hy"] / ay
    den = hx * hx + hy * hy + nh * nh
    ds = 1.0 / (math.pi * ax * ay * den * den)
    lx, ly, vx, vy = _dot(l, x) * ax, _dot(l, y) * ay, _dot(v, x) * ax, _dot(v, y) * ay
    gs = _g_over_4nn(nl, lx * lx + ly * ly) * _g_over_4nn(nv, vx * vx + vy * vy)
    return where(nh > 0.0, ds * gs, 0.0)


# ---------------------------------------------------------------------------------------------
# C code generation
# ---------------------------------------------------------------------------------------------

_PRELUDE = r"""
#include <math.h>
#include <stdint.h>
#include <string.h>
#if defined(__AVX512F__)
#include <immintrin.h>
#endif
/* Natural log for positive normal doubles, branch-free so the lane loop vectorises
   (a libm call would not): log(m 2^e) = e ln2 + 2 atanh((m-1)/(m+1)), m in [sqrt(1/2), sqrt(2)),
   series to z^10 (|z| <= 0.0295): error a few ulp of double. */
static inline double tb_log(double x) {
    uint64_t b; memcpy(&b, &x, 8);
    int64_t eb = (int64_t)(b >> 52);
    uint64_t mb = (b & 0x000fffffffffffffULL) | 0x3ff0000000000000ULL;
    double m0; memcpy(&m0, &mb, 8);
    double e0 = (double)(eb - 1023);
    double m = m0 > 1.4142135623730951 ? m0 * 0.5 : m0;
    double e = m0 > 1.4142135623730951 ? e0 + 1.0 : e0;
    double s = (m - 1.0) / (m + 1.0), z = s * s;
    double p = 1.0/21.0;
    p = p * z + 1.0/19.0; p = p * z + 1.0/17.0; p = p * z + 1.0/15.0; p = p * z + 1.0/13.0;
    p = p * z + 1.0/11.0; p = p * z + 1.0/9.0; p = p * z + 1.0/7.0; p = p * z + 1.0/5.0;
    p = p * z + 1.0/3.0;
    double lm = 2.0 * s + 2.0 * s * (z * p);
    return e * 6.93147180369123816490e-01 + (e * 1.90821492927058770002e-10 + lm);
}
/* log(1 + t): Goldberg's trick, exact where 1 + t is. */
static inline double tb_log1p(double t) {
    double u = 1.0 + t;
    double d = u - 1.0;
    double lu = tb_log(u == 1.0 ? 2.0 : u);
    return u == 1.0 ? t : lu * (t / d);
}
/* float32 versions, float-only arithmetic (mixing float and double masks in one select
   stops gcc 12 from vectorising the lane loop): series to z^5, error ~1 ulp of float. */
static inline float tb_logf(float x) {
    uint32_t b; memcpy(&b, &x, 4);
    float e0 = (float)((int32_t)(b >> 23) - 127);
    uint32_t mb = (b & 0x007fffffU) | 0x3f800000U;
    float m0; memcpy(&m0, &mb, 4);
    float m = m0 > 1.41421356f ? m0 * 0.5f : m0;
    float e = m0 > 1.41421356f ? e0 + 1.0f : e0;
    float s = (m - 1.0f) / (m + 1.0f), z = s * s;
    float p = 1.0f / 11.0f;
    p = p * z + 1.0f / 9.0f; p = p * z + 1.0f / 7.0f; p = p * z + 1.0f / 5.0f; p = p * z + 1.0f / 3.0f;
    float lm = 2.0f * s + 2.0f * s * (z * p);
    return e * 0.693145751953125f + (e * 1.428606820309417e-06f + lm);
}
static inline float tb_log1pf(float t) {
    float u = 1.0f + t;
    float d = u - 1.0f;
    float lu = tb_logf(u == 1.0f ? 2.0f : u);
    return u == 1.0f ? t : lu * (t / d);
}
"""


def _lit(x: float) -> str:
    r = repr(float(x))
    if r in ("inf", "-inf", "nan"):
        raise ValueError(x)
    return r


class _Emitter:
    def __init__(self, ctype: str):
        self.R = ctype

    def t(self, kind):
        return {"r": "R", "d": "double", "p": "double", "b": "int"}[kind]

    def sel(self, c: _Node, x: str, y: str, v) -> str:
        """``c ? x : y`` with ``and`` masks expanded into nested selects (a ``&&`` becomes a
        boolean phi that gcc 12 cannot vectorise)."""
        if c.op == "and":
            return self.sel(c.args[0], self.sel(c.args[1], x, y, v), y, v)
        return f"({v(c)} ? {x} : {y})"

    def expr(self, nd: _Node, v) -> str:
        a = [v(x) for x in nd.args]
        op = nd.op
        T = self.t(nd.kind)
        if op == "const":
            return f"(({T}){_lit(nd.attr)})" if nd.kind == "r" else _lit(nd.attr)
        if op == "in":
            return nd.attr["load"]
        if op == "P":
            return f"P[{nd.attr}]"
        if op in ("add", "sub", "mul", "div"):
            sym = {"add": "+", "sub": "-", "mul": "*", "div": "/"}[op]
            return f"{a[0]} {sym} {a[1]}"
        if op == "neg":
            return f"-{a[0]}"
        if op == "recip":
            return f"(({T})1) / {a[0]}"
        if op == "sqrt":
            return f"SQRT_{nd.kind.upper()}({a[0]})" if nd.kind == "r" else f"sqrt({a[0]})"
        if op == "rsqrt":
            return (f"((R)1) / SQRT_R({a[0]})" if nd.kind == "r" else f"1.0 / sqrt({a[0]})")
        if op in ("log", "log1p"):
            fn = f"tb_{op}" + ("f" if nd.kind == "r" and self.R == "float" else "")
            return f"{fn}({a[0]})"
        if op == "abs":
            return f"({a[0]} < 0 ? -{a[0]} : {a[0]})"
        if op == "maxc":
            return f"({a[0]} < {a[1]} ? {a[1]} : {a[0]})"
        if op == "pmax":
            return f"({a[1]} > {a[0]} ? {a[1]} : {a[0]})"
        if op == "clamp":
            return f"({a[0]} < {a[1]} ? {a[1]} : ({a[0]} > {a[2]} ? {a[2]} : {a[0]}))"
        if op == "where":
            return self.sel(nd.args[0], a[1], a[2], v)
        if op == "gt":
            return f"({a[0]} > {a[1]})"
        if op == "lt":
            return f"({a[0]} < {a[1]})"
        if op == "and":
            return "(and-masks are expanded by sel)"
        if op == "stopgrad":
            return a[0]
        if op == "tod":
            return f"(double){a[0]}"
        if op == "tor":
            return f"(R){a[0]}"
        raise NotImplementedError(op)

    def adjoint(self, nd: _Node, g: str, v) -> list:
        """Contributions ``(arg_index, expr)`` of ``nd``'s adjoint ``g`` to its arguments."""
        a = [v(x) for x in nd.args]
        me = v(nd)
        op = nd.op
        T = self.t(nd.kind)
        if op == "add":
            return [(0, g), (1, g)]
        if op == "sub":
            return [(0, g), (1, f"-{g}")]
        if op == "mul":
            return [(0, f"{g} * {a[1]}"), (1, f"{g} * {a[0]}")]
        if op == "div":
            return [(0, f"{g} / {a[1]}"), (1, f"-{g} * (({a[0]} / {a[1]}) / {a[1]})")]
        if op == "neg":
            return [(0, f"-{g}")]
        if op == "recip":
            return [(0, f"-{g} * ({me} * {me})")]
        if op == "sqrt":
            return [(0, f"{g} / ((({T})2) * {me})")]
        if op == "rsqrt":
            return [(0, f"(({T})-0.5) * {g} * ({me} * {me} * {me})")]
        if op == "log":
            return [(0, f"{g} / {a[0]}")]
        if op == "log1p":
            return [(0, f"{g} / ({a[0]} + (({T})1))")]
        if op == "abs":
            return [(0, f"({a[0]} < 0 ? -{g} : ({a[0]} > 0 ? {g} : ({T})0))")]
        if op == "maxc":
            return [(0, f"({a[0]} >= {a[1]} ? {g} : ({T})0)")]
        if op == "clamp":
            return [(0, f"({a[0]} >= {a[1]} ? ({a[0]} <= {a[2]} ? {g} : ({T})0) : ({T})0)")]
        if op == "where":
            c = nd.args[0]
            return [(1, self.sel(c, g, f"({T})0", v)), (2, self.sel(c, f"({T})0", g, v))]
        if op == "tod":
            return [(0, f"(R){g}")]
        if op == "tor":
            return [(0, f"(double){g}")]
        return []


_BLOCK = 512  # lanes per block of the kernels' loops (stack buffers of the pre-loop)
_CHUNK_BLOCKS = 8  # blocks per OpenMP work item (dynamic schedule: a core slowed by other load takes fewer)


def _generate(spec: "_KernelSpec", backward: bool) -> str:
    """C source of the forward (or backward) kernel of one kernel family."""
    global _G
    _G = _Graph()
    try:
        inp = {}
        loads = []  # (node, tensor index, channel)
        for k, (name, mode, C) in enumerate(spec.tensors):
            chans = []
            for c in range(C):
                if mode == "full":
                    idx = f"i * {C} + {c}" if C > 1 else "i"
                elif mode == "b1":
                    idx = f"{c}"
                else:
                    idx = "0"
                nd = _Node("in", (), "r", {"load": f"p{k}[{idx}]", "k": k, "c": c})
                loads.append(nd)
                chans.append(nd)
            inp[name] = chans if C == 3 else chans[0]
        for j, name in enumerate(spec.floats):
            inp[name] = _Node("P", (), "p", j)
        for name in SCALAR_NAMES:
            inp.setdefault(name, None)
        # A Python-float base colour becomes a 0-d compute-dtype tensor, as in eager.
        if not isinstance(inp.get("base_color"), list):
            b = tor(inp["base_color"])
            inp["base_color"] = [b, b, b]
        outs = _build_principled(inp, spec.active, spec.need_tint, spec.frame, spec.hi_double)
        nodes = _G.nodes
    finally:
        _G = None

    em = _Emitter(spec.ctype)
    names = {}

    def v(nd):
        return names[nd.id] if isinstance(nd, _Node) else _lit(nd)

    # keep only nodes that the outputs depend on
    live = set()
    stack = [o for o in outs if isinstance(o, _Node)]
    while stack:
        nd = stack.pop()
        if nd.id in live:
            continue
        live.add(nd.id)
        stack.extend(a for a in nd.args if isinstance(a, _Node))
    order = [nd for nd in nodes if nd.id in live]

    # log/log1p nodes are evaluated in a pre-loop over each block of lanes and read back
    # from a small stack buffer: with the (inlined) log in the main loop gcc 12 gives up
    # vectorising it, and the logs only depend on a few inputs (the clearcoat gloss).
    logs = [nd for nd in order if nd.op in ("log", "log1p")]
    pre_live = set()
    stack = [a for nd in logs for a in nd.args if isinstance(a, _Node)]
    while stack:
        nd = stack.pop()
        if nd.id in pre_live:
            continue
        pre_live.add(nd.id)
        stack.extend(a for a in nd.args if isinstance(a, _Node))

    def emit(nodes_, out_lines):
        for nd in nodes_:
            if nd.kind == "b":  # masks are inlined: int-typed mask variables stop gcc vectorising
                names[nd.id] = f"({em.expr(nd, v)})"
                continue
            names[nd.id] = f"v{nd.id}"
            out_lines.append(f"const {em.t(nd.kind)} v{nd.id} = {em.expr(nd, v)};")

    pre = []
    emit([nd for nd in order if nd.id in pre_live], pre)
    for j, nd in enumerate(logs):
        pre.append(f"lg{j}[i - b0] = {em.expr(nd, v)};")
    names.clear()
    body = []
    for j, nd in enumerate(logs):
        names[nd.id] = f"v{nd.id}"
    cut = {nd.id for nd in logs}
    emit([nd for nd in order if nd.id not in cut], body)
    body = [f"const {em.t(nd.kind)} v{nd.id} = lg{j}[i - b0];" for j, nd in enumerate(logs)] + body

    ntens = len(spec.tensors)
    decl = [f"const R* __restrict p{k} = (const R*)in[{k}];" for k in range(ntens)]
    if not backward:
        for c, o in enumerate(outs):
            body.append(f"ob{c}[i - b0] = {v(o)};")
        sig = "void tb_fwd(long n, void** in, const double* P, R* __restrict out, int nthreads)"
    else:
        gsl, gsc = spec.go_strides
        contrib: dict[int, list[str]] = {}
        for c, o in enumerate(outs):
            if isinstance(o, _Node) and o.grad:
                contrib.setdefault(o.id, []).append(f"go[i * {gsl} + {c * gsc}]")
        for nd in reversed(order):
            if not nd.grad or nd.id not in contrib or nd.op == "in":
                continue
            gname = f"g{nd.id}"
            body.append(f"const {em.t(nd.kind)} {gname} = {' + '.join(contrib[nd.id])};")
            for idx, e in em.adjoint(nd, gname, v):
                arg = nd.args[idx]
                if isinstance(arg, _Node) and arg.grad:
                    contrib.setdefault(arg.id, []).append(f"({e})")
        # Gradients are always written lane-dense (chunk buffers for broadcast inputs); an
        # input with no path to the output gets none (None in autograd, as in eager).
        written = []
        for k, (name, mode, C) in enumerate(spec.tensors):
            if k not in spec.grad_mask or not any(nd.attr["k"] == k and nd.id in contrib for nd in loads):
                continue
            written.append(k)
            for c in range(C):
                terms = []
                for nd in loads:
                    if nd.attr["k"] == k and nd.attr["c"] == c and nd.id in contrib:
                        terms.extend(contrib[nd.id])
                val = " + ".join(terms) if terms else "(R)0"
                body.append(f"gp{k}[i * {C} + {c}] = {val};")
        spec.written = tuple(written)
        decl += [f"R* __restrict gp{k} = (R*)gout[{k}];" for k in written]
        sig = ("void tb_bwd(long n, void** in, const double* P, const R* __restrict go, void** gout, "
               "int nthreads)")

    src = [
        _PRELUDE,
        f"typedef {spec.ctype} R;",
        "#define SQRT_R(x) " + ("__builtin_sqrtf(x)" if spec.ctype == "float" else "__builtin_sqrt(x)"),
        sig + " {",
        *("  " + d for d in decl),
        f"  #pragma omp parallel for schedule(dynamic, {_CHUNK_BLOCKS}) num_threads(nthreads)",
        f"  for (long b0 = 0; b0 < n; b0 += {_BLOCK}) {{",
        f"    const long b1 = b0 + {_BLOCK} < n ? b0 + {_BLOCK} : n;",
        *(f"    {'float' if nd.kind == 'r' and spec.ctype == 'float' else 'double'} lg{j}[{_BLOCK}];"
          for j, nd in enumerate(logs)),
        *(["    #pragma GCC ivdep", "    for (long i = b0; i < b1; ++i) {", *("      " + b for b in pre), "    }"]
          if logs else []),
        *([f"    R ob0[{_BLOCK}], ob1[{_BLOCK}], ob2[{_BLOCK}];"] if not backward else []),
        "    #pragma GCC ivdep",
        "    for (long i = b0; i < b1; ++i) {",
        *("      " + b for b in body),
        "    }",
        *(_store_block(spec.ctype) if not backward else []),
        "  }",
        "}",
    ]
    return "\n".join(src) + "\n"


def _interleave_indices(k: int) -> tuple[list, list]:
    """permutex2var indices building the k-th 16-float vector of an RGB-interleaved block."""
    first, second = [], []
    for e in range(16):
        j, ch = divmod(16 * k + e, 3)
        first.append(j if ch == 0 else (16 + j if ch == 1 else 0))
        second.append(16 + j if ch == 2 else e)
    return first, second


def _store_block(ctype: str) -> list:
    """Write a block's three planar output channels interleaved into ``out``.

    float32 with AVX-512: the interleave is done with two permutes per vector and written with
    streaming stores (the output is not read back; skipping the read-for-ownership saves ~10 %
    of the forward's memory traffic). Otherwise a plain loop.
    """
    plain = ["    for (long i = b0; i < b1; ++i) {",
             "      out[i * 3 + 0] = ob0[i - b0]; out[i * 3 + 1] = ob1[i - b0]; out[i * 3 + 2] = ob2[i - b0];",
             "    }"]
    if ctype != "float":
        return plain
    lines = ["#if defined(__AVX512F__)",
             f"    if (b1 - b0 == {_BLOCK} && (((uintptr_t)(out + 3 * b0)) & 63) == 0) {{"]
    for k in range(3):
        a, b = _interleave_indices(k)
        lines.append(f"      const __m512i I{k} = _mm512_set_epi32({', '.join(str(x) for x in reversed(a))});")
        lines.append(f"      const __m512i J{k} = _mm512_set_epi32({', '.join(str(x) for x in reversed(b))});")
    lines += [f"      for (long j = 0; j < {_BLOCK}; j += 16) {{",
              "        const __m512 a = _mm512_loadu_ps(ob0 + j), b = _mm512_loadu_ps(ob1 + j), c = _mm512_loadu_ps(ob2 + j);",
              *(f"        _mm512_stream_ps(out + 3 * (b0 + j) + {16 * k}, "
                f"_mm512_permutex2var_ps(_mm512_permutex2var_ps(a, I{k}, b), J{k}, c));" for k in range(3)),
              "      }",
              "      _mm_sfence();",
              "    } else",
              "#endif",
              "    {", *("  " + x for x in plain), "    }"]
    return lines


# ---------------------------------------------------------------------------------------------
# Compilation and caching
# ---------------------------------------------------------------------------------------------

class _KernelSpec:
    """Everything that changes the generated code (and nothing else)."""

    def __init__(self, ctype, tensors, floats, active, need_tint, frame, go_strides=(3, 1), grad_mask=()):
        self.ctype = ctype
        self.hi_double = ctype == "float"
        self.tensors = tuple(tensors)  # (name, mode, C)
        self.floats = tuple(floats)
        self.active = tuple(active)
        self.need_tint = bool(need_tint)
        self.frame = bool(frame)
        self.go_strides = tuple(go_strides)
        self.grad_mask = tuple(grad_mask)

    def key(self, backward):
        base = (self.ctype, self.tensors, self.floats, self.active, self.need_tint, self.frame)
        return base + ((self.go_strides, self.grad_mask) if backward else ())


# Building, caching and loading live in :mod:`torchbrdf.kernels.build` (per-user cache, atomic
# writes, validated loads, locks, PyTorch's OpenMP runtime); these names stay for callers.
_CFLAGS = _build.CFLAGS
_lock = threading.Lock()
_libs: dict = {}  # spec key -> (cdll, fn, written)
_failed: set = set()
kernel_cache_dir = _build.kernel_cache_dir
available = _build.available
_compiler = _build._compiler
_machine_tag = _build._machine_tag

_FWD_ARGS = [ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
_BWD_ARGS = [ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]


def compiled_kernels() -> int:
    """Number of kernel libraries loaded in this process."""
    return len(_libs)


def _load(spec: _KernelSpec, backward: bool):
    """``(cdll, fn, written)`` for the kernel of ``spec``, or None (then run eager)."""
    key = spec.key(backward)
    lib = _libs.get(key)
    if lib is not None:
        return lib
    with _lock:
        lib = _libs.get(key)
        if lib is not None:
            return lib
        if key in _failed:
            return None
        src = _generate(spec, backward)
        written = getattr(spec, "written", ())
        sym = "tb_bwd" if backward else "tb_fwd"
        cdll = _build.load_kernel(src, f"principled_{'bwd' if backward else 'fwd'}",
                                  {sym: (_BWD_ARGS if backward else _FWD_ARGS, None)})
        if cdll is None:
            _failed.add(key)
            return None
        lib = (cdll, getattr(cdll, sym), written)
        _libs[key] = lib
        return lib


# ---------------------------------------------------------------------------------------------
# Tensor plumbing and the autograd Function
# ---------------------------------------------------------------------------------------------

class _BufferPool:
    """Recycles the large output/gradient buffers of the fused path (a small caching allocator).

    torch's CPU allocator returns every large block to the OS, so each call would pay a page
    fault per 4 KiB of fresh output and gradient memory — measured ~300 ms for the 0.45 GiB of
    gradients at N = 2^22, more than the kernels themselves. Buffers handed out here are
    anonymous ``mmap`` regions wrapped by ``torch.frombuffer``; when the last tensor using one
    is freed it comes back to the pool (at most ``TORCHBRDF_POOL_MB`` MiB, default 2048, are
    kept; :func:`empty_cache` drops them). Only blocks of at least 1 MiB are pooled.
    """

    MIN_BYTES = 1 << 20

    def __init__(self):
        self.free: dict = {}
        self.cached = 0
        self.lock = threading.Lock()

    def limit(self) -> int:
        try:
            return int(os.environ.get("TORCHBRDF_POOL_MB", "2048")) << 20
        except ValueError:
            return 2048 << 20

    def empty(self, shape, dtype) -> Tensor:
        n = math.prod(shape)
        nbytes = n * torch.empty((), dtype=dtype).element_size()
        if nbytes < self.MIN_BYTES or self.limit() <= 0:
            return torch.empty(shape, dtype=dtype)
        with self.lock:
            lst = self.free.get(nbytes)
            mm = lst.pop() if lst else None
            if mm is not None:
                self.cached -= nbytes
        if mm is None:
            mm = mmap.mmap(-1, nbytes)
        mv = memoryview(mm)
        t = torch.frombuffer(mv, dtype=dtype, count=n).view(shape)
        weakref.finalize(mv, self._release, mm, nbytes)
        return t

    def _release(self, mm, nbytes):
        with self.lock:
            if self.cached + nbytes <= self.limit():
                self.free.setdefault(nbytes, []).append(mm)
                self.cached += nbytes
                return
        mm.close()

    def clear(self):
        with self.lock:
            lists, self.free, self.cached = self.free, {}, 0
        for lst in lists.values():
            for mm in lst:
                mm.close()


_pool = _BufferPool()


def empty_cache() -> None:
    """Release the fused path's cached output/gradient buffers to the OS."""
    _pool.clear()


# Lanes per backward chunk when some input is broadcast (its per-lane gradients are
# reduced chunk by chunk, so the buffers stay small: 2^16 lanes × 3 × 8 B = 1.5 MiB).
BWD_CHUNK = 1 << 16


def _flatten(t: Tensor, C: int, batch: tuple, N: int):
    """View ``t`` as ``(N, C)`` lanes: mode 'full' (lane-dense), 'b1'/'b0' (same for all lanes)."""
    e = t.expand(*batch, C) if t.dim() > 0 else t.reshape(1).expand(*batch, C)
    try:
        f = e.view(N, C)
    except RuntimeError:
        f = e.reshape(N, C)
    ls, cs = f.stride()
    if N > 1 and ls == 0:
        if C == 1 or cs == 1:
            return f, "b1", C
        if cs == 0:
            return f, "b0", C
    if (ls == C or N == 1) and (cs == 1 or C == 1):
        return f, "full", C
    return f.contiguous(), "full", C


class _Plan:
    """One call's layout: which inputs are tensors and how they map to lanes."""

    def __init__(self, c: dict, active, need_tint, frame):
        names = [k for k in ("l", "v", "n") + (("x", "y") if frame else ()) + ("base_color",) + SCALAR_NAMES]
        self.tensor_names = [k for k in names if isinstance(c.get(k), Tensor)]
        self.float_names = [k for k in names if k not in self.tensor_names]
        tens = [c[k] for k in self.tensor_names]
        shapes = [t.shape[:-1] if t.dim() > 0 else () for t in tens]
        self.batch = tuple(torch.broadcast_shapes(*shapes))
        self.N = math.prod(self.batch)
        self.dtype = c["l"].dtype
        self.device = c["l"].device
        self.floats = [float(c[k]) for k in self.float_names]
        self.active, self.need_tint, self.frame = tuple(active), need_tint, frame

    def flat(self, tensors):
        out = [_flatten(t, 1 if k in SCALAR_NAMES else 3, self.batch, self.N)
               for k, t in zip(self.tensor_names, tensors)]
        modes = tuple((k, m, C) for k, (_, m, C) in zip(self.tensor_names, out))
        return [f for f, _, _ in out], modes

    def spec(self, modes, go_strides=(3, 1), grad_mask=()):
        ctype = "float" if self.dtype == torch.float32 else "double"
        return _KernelSpec(ctype, modes, self.float_names, self.active, self.need_tint, self.frame,
                           go_strides, grad_mask)


def _ptrs(ts):
    arr = (ctypes.c_void_p * max(1, len(ts)))()
    for i, t in enumerate(ts):
        arr[i] = t.data_ptr() if t is not None else None
    return arr


def _dparams(vals):
    return (ctypes.c_double * max(1, len(vals)))(*vals)


class _PrincipledFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, plan: _Plan, fwd, modes, *tensors):
        flat, _ = plan.flat(tensors)
        out = _pool.empty((plan.N, 3), plan.dtype)
        fn = fwd[1]
        fn(plan.N, _ptrs(flat), _dparams(plan.floats), out.data_ptr(), torch.get_num_threads())
        ctx.plan = plan
        ctx.modes = modes
        ctx.save_for_backward(*tensors)
        return out.view(*plan.batch, 3)

    @staticmethod
    def backward(ctx, grad_out):
        plan: _Plan = ctx.plan
        tensors = ctx.saved_tensors
        need = [i for i, t in enumerate(tensors) if ctx.needs_input_grad[3 + i]]
        if not need:
            return (None,) * (3 + len(tensors))
        if torch.is_grad_enabled():
            return (None, None, None) + _eager_backward(plan, tensors, grad_out, need)
        go = grad_out.reshape(plan.N, 3) if grad_out.shape == (*plan.batch, 3) else grad_out.expand(*plan.batch, 3).reshape(plan.N, 3)
        if go.dtype != plan.dtype:
            go = go.to(plan.dtype)
        gls, gcs = go.stride()
        if plan.N == 1:
            gls = 3
        if (gls, gcs) not in ((3, 1), (0, 0), (0, 1)):
            go = go.contiguous()
            gls, gcs = 3, 1
        flat, modes = plan.flat(tensors)
        spec = plan.spec(modes, (gls, gcs), tuple(need))
        lib = _load(spec, backward=True)
        if lib is None:  # compiler vanished between forward and backward: do it eagerly
            return (None, None, None) + _eager_backward(plan, tensors, grad_out, need)
        fn, written = lib[1], set(lib[2])
        need = [i for i in need if i in written]
        P = _dparams(plan.floats)
        nt = torch.get_num_threads()
        grads: list = [None] * len(tensors)
        full = {i: _pool.empty((plan.N, modes[i][2]), plan.dtype) for i in need if modes[i][1] == "full"}
        red = {i: torch.zeros(modes[i][2], dtype=plan.dtype, device=plan.device)
               for i in need if modes[i][1] != "full"}
        chunk = plan.N if not red else BWD_CHUNK
        bufs = {i: torch.empty(min(chunk, plan.N), modes[i][2], dtype=plan.dtype) for i in red}
        item = flat[0].element_size()
        for s in range(0, plan.N, chunk):
            m = min(chunk, plan.N - s)
            ins = []
            for f, (_, mode, C) in zip(flat, modes):
                ins.append(f.data_ptr() + (s * C * item if mode == "full" else 0))
            gouts = []
            for i in range(len(tensors)):
                if i in full:
                    gouts.append(full[i].data_ptr() + s * modes[i][2] * item)
                elif i in red:
                    gouts.append(bufs[i].data_ptr())
                else:
                    gouts.append(None)
            go_ptr = go.data_ptr() + (s * 3 * item if gls == 3 else 0)
            in_arr = (ctypes.c_void_p * len(ins))(*ins)
            g_arr = (ctypes.c_void_p * len(gouts))(*gouts)
            fn(m, in_arr, P, go_ptr, g_arr, nt)
            for i in red:
                red[i] += bufs[i][:m].sum(0)
        for i in need:
            t = tensors[i]
            C = modes[i][2]
            if i in full:
                g = full[i].view(*plan.batch, C)
            else:
                g = red[i] if modes[i][1] == "b1" else red[i].sum().reshape(1)
            grads[i] = _reduce_to(g, t, plan.batch, C)
        return (None, None, None) + tuple(grads)


def _reduce_to(g: Tensor, t: Tensor, batch, C) -> Tensor:
    """Sum a lane gradient ``g`` down to the shape of input ``t``."""
    if g.dim() == 1:  # a broadcast input, already summed over the lanes: (C,) or (1,)
        return g.reshape(t.shape)
    return g.sum_to_size(t.shape) if tuple(g.shape) != tuple(t.shape) else g


def _eager_backward(plan: _Plan, tensors, grad_out, need):
    """A differentiable backward (``create_graph=True``): rebuild the eager graph."""
    from torchbrdf.brdf.principled import _principled_eager

    c = dict(zip(plan.float_names, plan.floats))
    c.update(dict(zip(plan.tensor_names, tensors)))
    c.setdefault("x", None)
    c.setdefault("y", None)
    with torch.enable_grad():
        out = _principled_eager(c, plan.active)
        wrt = [tensors[i] for i in need]
        gs = torch.autograd.grad(out, wrt, grad_out, create_graph=True, allow_unused=True)
    grads = [None] * len(tensors)
    for i, g in zip(need, gs):
        grads[i] = g if g is not None else torch.zeros_like(tensors[i])
    return tuple(grads)


def principled_fast(c: dict, active, need_tint: bool, frame: bool):
    """Fused evaluation on checked, compute-dtype CPU inputs ``c`` (see ``principled._prepare``).

    ``x``/``y`` must already be filled in when ``frame`` is true. Returns ``(*, 3)`` or
    ``None`` when the kernel cannot be built (the caller then runs eager).
    """
    plan = _Plan(c, active, need_tint, frame)
    tensors = [c[k] for k in plan.tensor_names]
    _, modes = plan.flat(tensors)
    fwd = _load(plan.spec(modes), backward=False)
    if fwd is None:
        return None
    return _PrincipledFunction.apply(plan, fwd, modes, *tensors)
