"""C code generation for the fused kernels: prints a traced graph (see :mod:`.trace`) as C.

:func:`generate` takes the kernel graph of one kernel family from :func:`.graphs.build` (the
formula traced, with the derivative transform the kernel needs) and prints its nodes as one
lane loop. Nothing here knows the formula or a derivative rule.

Kernels (``R`` is float or double; ``in`` holds one pointer per tensor input, ``P`` the runtime
Python floats):

* ``tb_fwd(n, in, P, out, nthreads)``: ``out`` ``(n, 3)``;
* ``tb_bwd(n, in, P, go, gout, nthreads)``: ``go`` the output gradient (strides
  ``spec.go_strides``), ``gout[k]`` a lane-dense ``(n, C_k)`` gradient of input ``k``;
* ``tb_jvp(n, in, P, tin, tout, nthreads)``: ``tin[j * T + i]`` the tangent ``j`` of the
  ``i``-th input of ``spec.tangent_inputs`` (``T`` of them), ``tout[j]`` its ``(n, 3)`` output
  tangent: several tangents in one pass over the primal computation (a slot whose tangent
  mode is ``"zero"`` is never read: that input has no tangent in that direction).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

from torchbrdf.kernels.graphs import build
from torchbrdf.kernels.trace import Graph, Node, live_order

if TYPE_CHECKING:  # fused imports this module at run time
    from torchbrdf.kernels.fused import KernelSpec

PRELUDE = r"""
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
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


def _exp2_source() -> str:
    """``tb_exp2`` / ``tb_exp2f``: ``2^x`` branch-free, so the lane loop vectorises (a libm call
    would not). ``2^x = 2^k 2^f`` with ``k`` = x rounded by the 1.5·2^52 (2^23) shift, ``|f| <= 1/2``,
    ``2^f`` its Taylor series in ``f ln 2`` (to f^13 in double, f^7 in float: truncation below
    0.1 ulp), ``2^k`` written into the exponent bits. ``x`` is clamped to the normal range
    ([-1022, 1023], float [-126, 127]): a smaller argument gives the smallest normal, not a
    subnormal or 0."""
    def one(name: str, real: str, bits: str, nbytes: int, lo: int, hi: int, shift: str,
            mantissa: int, deg: int, suffix: str) -> str:
        cs = [math.log(2.0) ** i / math.factorial(i) for i in range(deg + 1)]
        horner = " ".join([f"p = {lit(cs[deg])}{suffix};"]
                          + [f"p = p * f + {lit(c)}{suffix};" for c in reversed(cs[:deg])])
        return rf"""
static inline {real} {name}({real} x) {{
    x = x < {lo}.0{suffix} ? {lo}.0{suffix} : (x > {hi}.0{suffix} ? {hi}.0{suffix} : x);
    const {real} kk = x + {shift}{suffix};
    const {real} f = x - (kk - {shift}{suffix});
    {bits} b; memcpy(&b, &kk, {nbytes});
    b = (b + {hi}) << {mantissa};
    {real} s; memcpy(&s, &b, {nbytes});
    {real} p; {horner}
    return p * s;
}}"""

    return (one("tb_exp2", "double", "uint64_t", 8, -1022, 1023, "6755399441055744.0", 52, 13, "")
            + one("tb_exp2f", "float", "uint32_t", 4, -126, 127, "12582912.0", 23, 7, "f") + "\n")


def lit(x: float) -> str:
    r = repr(float(x))
    if r in ("inf", "-inf", "nan"):
        raise ValueError(x)
    return r


#: ``tb_exp2``/``tb_exp2f``, printed only into kernels whose graph has an ``exp2`` (the others'
#: sources, hence their cache keys, stay as they were).
EXP2_PRELUDE = _exp2_source()

_CTYPE = {"d": "double", "p": "double", "b": "int"}
_BINOP = {"add": "+", "sub": "-", "mul": "*", "div": "/"}
_CMP = {"gt": ">", "lt": "<", "ge": ">=", "le": "<=", "eq": "=="}


class Emitter:
    """Prints nodes as C for compute type ``ctype``; ``load(attr)`` prints an ``in`` node's load."""

    def __init__(self, ctype: str, load: Callable[[dict], str]) -> None:
        self.R = ctype
        self.load = load

    def t(self, kind: str) -> str:
        return "R" if kind == "r" else _CTYPE[kind]

    def sel(self, c: Node, x: str, y: str, v: Callable[[Any], str]) -> str:
        """``c ? x : y`` with ``and`` masks expanded into nested selects.

        A ``&&`` becomes a boolean phi that gcc 12 cannot vectorise.
        """
        if c.op == "and":
            # The operands of a mask are masks (nodes).
            return self.sel(cast(Node, c.args[0]), self.sel(cast(Node, c.args[1]), x, y, v), y, v)
        return f"({v(c)} ? {x} : {y})"

    def expr(self, nd: Node, v: Callable[[Any], str]) -> str:
        a = [v(x) for x in nd.args]
        op = nd.op
        T = self.t(nd.kind)
        if op == "const":
            return f"(({T}){lit(nd.attr)})" if nd.kind == "r" else lit(nd.attr)
        if op == "in":
            return self.load(nd.attr)
        if op == "P":
            return f"P[{nd.attr}]"
        if op in _BINOP:
            return f"{a[0]} {_BINOP[op]} {a[1]}"
        if op in _CMP:
            return f"({a[0]} {_CMP[op]} {a[1]})"
        if op == "neg":
            return f"-{a[0]}"
        if op == "recip":
            return f"(({T})1) / {a[0]}"
        if op == "sqrt":
            return f"SQRT_R({a[0]})" if nd.kind == "r" else f"sqrt({a[0]})"
        if op == "rsqrt":
            return f"((R)1) / SQRT_R({a[0]})" if nd.kind == "r" else f"1.0 / sqrt({a[0]})"
        if op in ("log", "log1p"):
            fn = f"tb_{op}" + ("f" if nd.kind == "r" and self.R == "float" else "")
            return f"{fn}({a[0]})"
        if op == "exp2":
            return f"tb_exp2{'f' if nd.kind == 'r' and self.R == 'float' else ''}({a[0]})"
        if op == "abs":
            return f"({a[0]} < 0 ? -{a[0]} : {a[0]})"
        if op == "max2":
            return f"({a[0]} < {a[1]} ? {a[1]} : {a[0]})"
        if op == "maxc":
            return f"({a[0]} < {a[1]} ? {a[1]} : {a[0]})"
        if op == "pmax":
            return f"({a[1]} > {a[0]} ? {a[1]} : {a[0]})"
        if op == "clamp":
            return f"({a[0]} < {a[1]} ? {a[1]} : ({a[0]} > {a[2]} ? {a[2]} : {a[0]}))"
        if op == "where":
            return self.sel(cast(Node, nd.args[0]), a[1], a[2], v)  # the mask is a node
        if op == "and":  # only printed inside selects, which expand it (see sel)
            return f"({a[0]} && {a[1]})"
        if op == "tod":
            return f"(double){a[0]}"
        if op == "tor":
            return f"(R){a[0]}"
        raise NotImplementedError(op)


_BLOCK = 512  # lanes per block of the kernels' loops (stack buffers of the pre-loop)
CHUNK_BLOCKS = 8  # blocks per OpenMP work item (dynamic schedule: a core slowed by other load takes fewer)


def lane_index(mode: str, C: int, c: int) -> str:
    if mode == "full":
        return f"i * {C} + {c}" if C > 1 else "i"
    return f"{c}" if mode == "b1" else "0"


def _load_expr(attr: dict, spec) -> str:
    """The C expression of a load node."""
    role = attr["role"]
    if attr.get("mode") == "s2":  # gathered per block by the pre-loop (see _gathers)
        return f"{_gather_buf(attr)}[i - b0]"
    if role == "x":
        return f"p{attr['k']}[{lane_index(attr['mode'], attr['C'], attr['c'])}]"
    if role == "go":
        gsl, gsc = spec.go_strides
        return f"go[i * {gsl} + {attr['c'] * gsc}]"
    return f"t{attr['j']}_{attr['i']}[{lane_index(attr['mode'], attr['C'], attr['c'])}]"


def _gather_buf(attr: dict) -> str:
    if attr["role"] == "x":
        return f"g{attr['k']}_{attr['c']}"
    return f"gt{attr['j']}_{attr['i']}_{attr['c']}"


def _gathers(spec, order) -> tuple[list[str], list[str], list[str]]:
    """Code for the inputs in mode 's2': ``(declarations, per-block buffers, pre-loop body)``.

    Mode 's2' is a value broadcast over one of two batch dims (see :func:`torchbrdf.kernels.layout.flatten`).

    Lane ``i`` is ``(q, r) = (i / B, i % B)`` and reads element ``q·sA + r·sB + c``; ``B`` and
    each input's ``(sA, sB)`` follow the runtime floats in ``P``, in slot order (the tensor
    inputs, then the tangents). A scalar pre-loop gathers a block's values into per-thread
    buffers, so the main loop (which an integer division would stop gcc from vectorising)
    reads them lane-dense. The buffers are one heap block per thread (``gs``, see
    :func:`_print`), not stack arrays: a JVP pass gathers up to ``TANGENTS_PER_PASS`` (12) tangents × every 's2'
    input's channels (~200 buffers, 0.8 MiB in double), more than a small thread stack holds.
    """
    slots: dict[tuple, int] = {}
    for k, (_, mode, _) in enumerate(spec.tensors):
        if mode == "s2":
            slots[("x", k)] = len(slots)
    T = len(spec.tangent_inputs)
    for j in range(spec.ntan):
        for i in range(T):
            if spec.tangent_modes[j * T + i] == "s2":
                slots[("t", j, i)] = len(slots)
    loads = [nd.attr for nd in order if nd.op == "in" and nd.attr.get("mode") == "s2"]
    if not loads:
        return [], [], []
    nf = len(spec.floats)
    decl = [f"const long SB = (long)P[{nf}];"]
    decl += [f"const long sa{m} = (long)P[{nf + 1 + 2 * m}], sb{m} = (long)P[{nf + 2 + 2 * m}];"
             for m in range(len(slots))]
    bufs: list[str] = []
    body: list[str] = []
    for a in loads:
        key = ("x", a["k"]) if a["role"] == "x" else ("t", a["j"], a["i"])
        m = slots[key]
        ptr = f"p{a['k']}" if a["role"] == "x" else f"t{a['j']}_{a['i']}"
        bufs.append(f"R* const {_gather_buf(a)} = gs + {len(bufs)} * {_BLOCK}L;")
        body.append(f"{_gather_buf(a)}[t - b0] = {ptr}[q * sa{m} + (r + t - i) * sb{m} + {a['c']}];")
    return decl, bufs, body


def _store_expr(target: tuple, spec) -> str:
    """The C lvalue of a store target."""
    if target[0] == "out":
        return f"ob{target[1]}[i - b0]"
    if target[0] == "grad":
        k, c = target[1:]
        return f"gp{k}[i * {spec.tensors[k][2]} + {c}]"
    j, c = target[1:]
    return f"to{j}[i * 3 + {c}]"


def generate(spec: KernelSpec, kind: str) -> str:
    """C source of one kernel (``kind`` = ``"fwd"``, ``"bwd"`` or ``"jvp"``) of a kernel family.

    For ``"bwd"`` it sets ``spec.written``: the inputs whose gradient the kernel writes.
    """
    kg = build(spec, kind)
    decl = [f"const R* __restrict p{k} = (const R*)in[{k}];" for k in range(len(spec.tensors))]
    if kind == "fwd":
        sig = "void tb_fwd(long n, void** in, const double* P, R* __restrict out, int nthreads)"
    elif kind == "bwd":
        spec.written = kg.written
        decl += [f"R* __restrict gp{k} = (R*)gout[{k}];" for k in kg.written]
        sig = ("void tb_bwd(long n, void** in, const double* P, const R* __restrict go, void** gout, "
               "int nthreads)")
    else:
        T = len(spec.tangent_inputs)
        for j in range(spec.ntan):
            decl += [f"const R* __restrict t{j}_{i} = (const R*)tin[{j * T + i}];" for i in range(T)
                     if spec.tangent_modes[j * T + i] != "zero"]  # "zero": pruned, never read
            decl.append(f"R* __restrict to{j} = (R*)tout[{j}];")
        sig = "void tb_jvp(long n, void** in, const double* P, void** tin, void** tout, int nthreads)"
    stores = [(_store_expr(t, spec), val) for t, val in kg.stores]
    return _print(spec, kg.graph, stores, decl, sig, kind == "fwd")


def _print(spec, g: Graph, stores, decl, sig, planar_out: bool) -> str:
    em = Emitter(spec.ctype, lambda attr: _load_expr(attr, spec))
    names: dict[int, str] = {}

    def v(nd):
        return names[nd.id] if isinstance(nd, Node) else (f"((R){lit(nd)})")

    order = live_order(g, [s for _, s in stores])
    gdecl, gbufs, gbody = _gathers(spec, order)
    decl = decl + gdecl
    # log/log1p nodes are evaluated in a pre-loop over each block of lanes and read back
    # from a small stack buffer: with the (inlined) log in the main loop gcc 12 gives up
    # vectorising it, and the logs only depend on a few inputs (the clearcoat gloss).
    logs = [nd for nd in order if nd.op in ("log", "log1p")]
    pre_ids = {nd.id for nd in live_order(g, [a for nd in logs for a in nd.args])}

    def emit(nodes_, out_lines):
        for nd in nodes_:
            if nd.kind == "b":  # masks are inlined: int-typed mask variables stop gcc vectorising
                names[nd.id] = f"({em.expr(nd, v)})"
                continue
            names[nd.id] = f"v{nd.id}"
            out_lines.append(f"const {em.t(nd.kind)} v{nd.id} = {em.expr(nd, v)};")

    pre: list[str] = []
    emit([nd for nd in order if nd.id in pre_ids], pre)
    for j, nd in enumerate(logs):
        pre.append(f"lg{j}[i - b0] = {em.expr(nd, v)};")
    names.clear()
    for nd in logs:
        names[nd.id] = f"v{nd.id}"
    cut = {nd.id for nd in logs}
    body = [f"const {em.t(nd.kind)} v{nd.id} = lg{j}[i - b0];" for j, nd in enumerate(logs)]
    emit([nd for nd in order if nd.id not in cut], body)
    body += [f"{ptr} = {v(val)};" for ptr, val in stores]

    src = [
        PRELUDE + (EXP2_PRELUDE if any(nd.op == "exp2" for nd in order) else ""),
        f"typedef {spec.ctype} R;",
        "#define SQRT_R(x) " + ("__builtin_sqrtf(x)" if spec.ctype == "float" else "__builtin_sqrt(x)"),
        sig + " {",
        *("  " + d for d in decl),
        # with gathers: one heap block of gather buffers per thread (see _gathers)
        *([f"  #pragma omp parallel num_threads(nthreads)", "  {",
           f"  R* const gs = (R*)malloc(sizeof(R) * {len(gbufs)} * {_BLOCK});",
           f"  #pragma omp for schedule(dynamic, {CHUNK_BLOCKS})"] if gbufs else
          [f"  #pragma omp parallel for schedule(dynamic, {CHUNK_BLOCKS}) num_threads(nthreads)"]),
        f"  for (long b0 = 0; b0 < n; b0 += {_BLOCK}) {{",
        f"    const long b1 = b0 + {_BLOCK} < n ? b0 + {_BLOCK} : n;",
        *("    " + b for b in gbufs),
        # one run of lanes per outer index q (r = 0 .. SB-1): the inner loop vectorises (a
        # broadcast when sB = 0, a strided read otherwise)
        *(["    for (long i = b0, q = b0 / SB, r = b0 - (b0 / SB) * SB; i < b1; ++q, r = 0) {",
           "      const long e = i + (SB - r) < b1 ? i + (SB - r) : b1;",
           "      for (long t = i; t < e; ++t) {", *("        " + b for b in gbody), "      }",
           "      i = e;", "    }"] if gbody else []),
        *(f"    {'float' if nd.kind == 'r' and spec.ctype == 'float' else 'double'} lg{j}[{_BLOCK}];"
          for j, nd in enumerate(logs)),
        *(["    #pragma GCC ivdep", "    for (long i = b0; i < b1; ++i) {", *("      " + b for b in pre), "    }"]
          if logs else []),
        *([f"    R ob0[{_BLOCK}], ob1[{_BLOCK}], ob2[{_BLOCK}];"] if planar_out else []),
        "    #pragma GCC ivdep",
        "    for (long i = b0; i < b1; ++i) {",
        *("      " + b for b in body),
        "    }",
        *(_store_block(spec.ctype) if planar_out else []),
        "  }",
        *(["  free(gs);", "  }"] if gbufs else []),
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
    streaming stores (the output is not read back, so the read-for-ownership is skipped).
    Otherwise a plain loop.
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
