"""The recovery's Gauss–Newton normal equations per pixel, as one light-loop kernel.

A fit of per-pixel unknowns ``x`` (``K`` of them) minimises ``Σ_lights Σ_channels r²`` with
``r`` the capture's log residual (:func:`torchbrdf.brdf.formula.capture_log_residual`:
``log(max(L + ε, ε/2)) − log_obs``). Per pixel its Gauss–Newton step needs the data cost
``Σ r²``, ``JᵀJ`` and ``Jᵀr`` with ``J = ∂r/∂x`` (rows: the lights' channels). Here they are
computed in one pass, with no ``(pixels, lights, K)`` Jacobian in memory:

* the residual formula is traced (:mod:`.trace`) with the per-pixel material and geometry as
  loads, the light's position and intensity as per-light uniforms and ``log_obs`` as a
  per-pixel-per-light load;
* its forward-mode derivatives along the ``K`` directions are the tracer's tangent transform
  (:func:`.trace.tangents`) seeded with the directions' tangents of the per-pixel inputs
  (``∂p/∂x_j``: the decode's Jacobian, given as input — the decode is the solver's one
  definition, differentiated by ``torch.func``);
* the products ``r²``, ``J_a · J_b`` (a ≤ b) and ``J_a · r`` are summed over the lights by the
  light-loop schedule (:mod:`.light_loop`: pixel-level terms once, the per-light terms inside
  the loop), which both the C and the Triton printer print.

A direction's tangent is read only for the input channels it moves (``pattern``), so the
decode's sparsity (each logit moves one channel) prunes the tangent graph. Nothing here knows
a formula or a derivative rule.

Output layout, per pixel (``W = 1 + K (K + 1) / 2 + K`` values): the cost, then ``JᵀJ``'s upper
triangle row by row (``(0,0), (0,1) … (0,K−1), (1,1) …``), then ``Jᵀr``; with ``residuals``,
then the residuals themselves, ``3 L`` values light-major (``3 j + c``), as they come.

Non-finite values follow the solver's rule: the cost sums the residuals as they are (a
non-finite one makes it non-finite), while ``JᵀJ`` and ``Jᵀr`` take a non-finite Jacobian
entry or residual as 0 (a pixel-light the model cannot evaluate adds nothing to the step).

The *cost-only* variant (``cost_only``, no unknowns) is what a search over candidate parameters
needs: each pixel's ``Σ r²`` (one value, ``W = 1``), with no ``(pixels, 3 L)`` residuals written
and read back. It sums the squares in float64 whatever the dtype (an accumulator per pixel in
registers; the float32 residuals are widened before squaring), and writes a non-finite sum as
+inf, the recovery's rule for a cost (``pixel_cost``): it never wins a comparison.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from torchbrdf.brdf import formula
from torchbrdf.brdf.formula import SCALAR_PARAMS
from torchbrdf.kernels.light_loop import Layout, LightLoop, LoopSchedule, acc_input, print_c, print_triton
from torchbrdf.kernels.trace import Graph, Node, TraceOps, Vec3, const, tangents

__all__ = ["NormalEqSpec", "schedule", "generate", "generate_triton", "width", "LIGHT_STRIDE", "CAMERA", "FAMILIES"]

FAMILIES = formula.LOOP_BRDFS  # the BRDFs it traces, by name

CAMERA = 3  # uniforms before the lights: the camera position
LIGHT_STRIDE = 6  # per light: position (3), intensity (3)
# Pixels per block of the C kernel: ~K × the pixel-level nodes' tangents live in stack arrays
# of this length (a few hundred arrays × 64 × 8 B: well inside a thread's stack). The inputs'
# interleaved (n, C) rows are copied into such arrays too (carry_loads): read once per pixel
# instead of with a stride once per pixel-light (docs/fast_path.md has the rates).
BLOCK = 64


def width(K: int) -> int:
    """Values per pixel of the output: the cost, ``JᵀJ``'s upper triangle, ``Jᵀr``."""
    return 1 + K * (K + 1) // 2 + K


class NormalEqSpec:
    """Everything that changes the generated normal-equations code.

    ``tensors``: ``(name, C)`` per per-pixel input (``pos``, ``n``, ``base_color``, scalar
    maps; lane-dense ``(n, C)``); ``floats``: names of the material parameters passed as
    runtime floats (then ``eps``, then the light count); ``K``: the unknowns per pixel;
    ``pattern``: per tensor input, the ``(direction, channel)`` pairs whose tangent is not
    zero, optionally ``(direction, channel, slot)``: the tangent tensor's row ``slot`` holds it
    (default the direction; directions that move disjoint channels can share a row, so the
    caller computes fewer tangents). An input with none has no tangent tensor. ``residuals``:
    each pixel's row also holds its ``3 L`` residuals (see the module docstring).
    ``cost_only``: only the cost, summed in float64, non-finite as +inf (``K`` must be 0).
    ``family``: the residual's BRDF (``capture_log_residual``'s ``family``).
    """

    def __init__(self, ctype: str, tensors: Iterable[tuple[str, int]], floats: Iterable[str],
                 active: Iterable[str], need_tint: bool, K: int,
                 pattern: Iterable[Iterable[tuple[int, ...]]], residuals: bool = False,
                 cost_only: bool = False, family: str = "principled") -> None:
        if family not in FAMILIES:
            raise ValueError(f"family: expected one of {FAMILIES}, got {family!r}")
        self.ctype = ctype
        self.family = family
        self.hi_double = ctype == "float"
        self.tensors = tuple(tensors)
        self.floats = tuple(floats)
        self.active = tuple(active)
        self.need_tint = bool(need_tint)
        self.K = int(K)
        self.residuals = bool(residuals)
        self.cost_only = bool(cost_only)
        if self.cost_only and (self.K or self.residuals):
            raise ValueError("NormalEqSpec: a cost-only kernel has no unknowns and writes no residuals")
        # (direction, channel, slot): slot = the tangent tensor's row holding it (default the direction)
        self.pattern = tuple(tuple(sorted((e[0], e[1], e[2] if len(e) > 2 else e[0]) for e in p))
                             for p in pattern)
        if len(self.pattern) != len(self.tensors):
            raise ValueError("NormalEqSpec: one pattern per tensor input")
        # the inputs with a tangent tensor, in tensor order: tangent argument m is tensor tan_inputs[m]
        self.tan_inputs = tuple(k for k, p in enumerate(self.pattern) if p)

    def key(self) -> tuple[Any, ...]:
        return ("normal_eq", self.ctype, self.tensors, self.floats, self.active, self.need_tint, self.K,
                self.pattern, self.residuals, self.cost_only, self.family,
                tuple(id(getattr(formula, f)) for f in ("capture_log_residual", "principled", "svbrdf_ggx",
                                                        "ggx_albedos")))


def _in(role: str, grad: bool = False, **attr) -> Node:
    return Node("in", (), "r", {"role": role, **attr}, grad=grad)


def schedule(spec: NormalEqSpec) -> LoopSchedule:
    """Trace the residual and its tangents; the light loop sums the normal-equation terms."""
    g = Graph()
    K = spec.K
    with g:
        ops = TraceOps(spec.hi_double)
        inp: dict[str, Any] = {}
        loads: list[Node] = []
        for k, (name, C) in enumerate(spec.tensors):
            chans = [_in("px", grad=True, k=k, c=c) for c in range(C)]
            loads += chans
            inp[name] = Vec3(chans) if C == 3 else chans[0]
        for j, name in enumerate(spec.floats):
            inp[name] = Node("P", (), "p", j)
        for name in ("x", "y", *SCALAR_PARAMS):
            inp.setdefault(name, None)
        u = [_in("light", c=c) for c in range(LIGHT_STRIDE)]
        inp.update({
            "camera": Vec3(_in("cam", c=c) for c in range(3)),
            "light_pos": Vec3(u[:3]), "light_int": Vec3(u[3:]),
            "log_obs": Vec3(_in("obs", c=c) for c in range(3)),
            "eps": Node("P", (), "p", len(spec.floats)),
        })
        r = list(formula.capture_log_residual(ops, inp, spec.active, spec.need_tint, False, spec.family).c)
        J: list[list[Any]] = []  # J[a][c]: ∂r_c/∂x_a (None: zero)
        for a in range(K):
            seeds = {}
            for nd in loads:
                k, c = nd.attr["k"], nd.attr["c"]
                for a2, c2, slot in spec.pattern[k]:
                    if (a2, c2) == (a, c):
                        seeds[nd.id] = _in("tan", k=k, c=c, j=slot, m=spec.tan_inputs.index(k))
            J.append(tangents(g, r, seeds) if seeds else [None, None, None])

        # the largest finite value of the kernel's type: |v| <= it is false for inf and NaN
        big = 3.4028234663852886e38 if spec.ctype == "float" else 1.7976931348623157e308

        def finite(x):
            return None if x is None else ops.where(ops.abs(x) <= big, x, 0.0)

        def dot(xs, ys):
            terms = [x * y for x, y in zip(xs, ys) if x is not None and y is not None]
            if not terms:
                return None
            s = terms[0]
            for t in terms[1:]:
                s = s + t
            return s

        if spec.cost_only:
            return _cost_schedule(g, ops, r)
        rf = [finite(x) for x in r]
        Jf = [[finite(x) for x in Ja] for Ja in J]
        values = [dot(r, r)]
        values += [dot(Jf[a], Jf[b]) for a in range(K) for b in range(a, K)]
        values += [dot(Jf[a], rf) for a in range(K)]
        accs = [(("out", i), v) for i, v in enumerate(values) if v is not None]
        acc_kind = {key: "r" for key, _ in accs}
        post: list[tuple[tuple[Any, ...], Node | None]] = [
            (("out", i), acc_input(("out", i)) if v is not None else None) for i, v in enumerate(values)]
        stores = {"point": [(("res", c), x) for c, x in enumerate(r)]} if spec.residuals else {}
    return LoopSchedule(g, {"point": accs}, acc_kind, post, stores=stores)


def _cost_schedule(g: Graph, ops: TraceOps, r: list[Any]) -> LoopSchedule:
    """The cost-only schedule: ``Σ r²`` over the lights in a float64 accumulator, non-finite as +inf.

    Called while ``g`` is being built (its nodes join it)."""
    hi = [ops.to_hi(x) for x in r]  # float32: widened to double before squaring (float64: as is)
    kind = "d" if ops.hi_double else "r"
    square = (hi[0] * hi[0] + hi[1] * hi[1]) + hi[2] * hi[2]
    acc = acc_input(("out", 0), kind)
    # +inf as 1/0 (a literal cannot print inf); NaN and +inf fail the comparison
    inf = Node("recip", (const(0.0, kind),), kind)
    cost = ops.to_compute(ops.where(acc <= 1.7976931348623157e308, acc, inf))
    assert isinstance(cost, Node)  # (an accumulator's read is never folded to a constant)
    return LoopSchedule(g, {"point": [(("out", 0), square)]}, {("out", 0): kind}, [(("out", 0), cost)])


def _layout(spec: NormalEqSpec) -> Layout:
    W = width(spec.K)
    row = f"({W} + 3 * L)" if spec.residuals else str(W)  # values per pixel

    def slot(s: tuple) -> str:  # a value's index in the pixel's row (a residual's: per light j)
        return f"{W} + 3 * j + {s[1]}" if s[0] == "res" else str(s[1])

    def address(a: dict) -> tuple[str, str, str]:  # (C array, Triton pointer, element offset)
        role = a["role"]
        if role == "px":
            C = spec.tensors[a["k"]][1]
            return f"p{a['k']}", f"x{a['k']}", f"i * {C} + {a['c']}"
        if role == "tan":
            C = spec.tensors[a["k"]][1]
            return f"t{a['m']}", f"t{a['m']}", f"({a['j']} * n + i) * {C} + {a['c']}"
        if role == "obs":
            return "lo", "lo", f"(i * L + j) * 3 + {a['c']}"
        name = "U" if role == "cam" else "u"
        return name, name, str(a["c"])

    def load_c(a: dict) -> str:
        array, _, offset = address(a)
        return f"{array}[{offset}]"

    def load_t(a: dict) -> str:  # per-pixel values are masked past the last pixel; uniforms are not
        _, pointer, offset = address(a)
        if a["role"] in ("px", "tan", "obs"):
            return f"tl.load({pointer} + ({offset}), mask=m, other=0.0)"
        return f"tl.load({pointer} + {offset})"

    return Layout(
        [LightLoop("point", "0", "L")], load_c, lambda s: f"out[i * {row} + {slot(s)}]", load_t,
        lambda s: f"out + (i * {row} + {slot(s)})", lit_roles=("light", "obs"), px_roles=("px", "tan", "obs"),
        skip=CAMERA, stride=LIGHT_STRIDE, block=BLOCK, carry_loads=True)


def generate(spec: NormalEqSpec) -> str:
    """C source of ``tb_ne(n, in, P, out, nthreads)``.

    ``in``: the per-pixel inputs ``(n, C)`` (``spec.tensors``), then one ``(S, n, C)`` tangent
    per input in ``spec.tan_inputs``, then ``log_obs`` ``(n, L, 3)``, then the uniform row
    ``[camera (3), (q, I) per light]``; ``P``: the runtime floats, ``eps``, the light count;
    ``out`` ``(n, W)`` (:func:`width`; ``(n, W + 3 L)`` with ``spec.residuals``).
    """
    T, M, F = len(spec.tensors), len(spec.tan_inputs), len(spec.floats)
    decl = [f"const R* __restrict p{k} = (const R*)in[{k}];" for k in range(T)]
    decl += [f"const R* __restrict t{m} = (const R*)in[{T + m}];" for m in range(M)]
    decl += [f"const R* __restrict lo = (const R*)in[{T + M}];",
             f"const R* __restrict U = (const R*)in[{T + M + 1}];",
             f"const long L = (long)P[{F + 1}];"]
    sig = "void tb_ne(long n, void** in, const double* P, R* __restrict out, int nthreads)"
    return print_c(spec.ctype, schedule(spec), _layout(spec), decl, sig)


def generate_triton(spec: NormalEqSpec, wide: bool = False) -> str:
    """Triton source of ``tb_ne(n, P, U, x0 .. x{T-1}, t0 .. t{M-1}, lo, out, L, BLOCK)`` (the
    same data as :func:`generate`; ``P`` a float64 tensor, ``L`` the light count)."""
    args = [f"x{k}" for k in range(len(spec.tensors))] + [f"t{m}" for m in range(len(spec.tan_inputs))]
    return print_triton(spec.ctype, schedule(spec), _layout(spec), "tb_ne", args + ["lo", "out", "L"], wide)
