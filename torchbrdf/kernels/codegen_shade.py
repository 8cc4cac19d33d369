"""Code generation for fused shading: geometry, a BRDF and the sum over lights in one loop.

C (:func:`generate`) and Triton (:func:`generate_triton`) print the same light-loop schedule
(:func:`schedule`, printed by :mod:`.light_loop`).

:func:`generate` traces :func:`torchbrdf.brdf.formula.view_direction` and the per-light terms
:func:`~torchbrdf.brdf.formula.point_light` / :func:`~torchbrdf.brdf.formula.directional_light`
(with :func:`~torchbrdf.brdf.formula.principled` or :func:`~torchbrdf.brdf.formula.svbrdf_ggx` as
the BRDF, ``ShadeSpec.family``) into ONE graph whose inputs are of three kinds:

* per-pixel loads (``px``): position, normal, tangent frame, material maps (and, in the
  backward, the output gradient);
* per-light uniforms (``lit``): ``u[0..2]`` position or direction, ``u[3..5]`` intensity or
  irradiance of light ``j`` (``u`` points into the uniform table);
* per-segment uniforms: the camera position ``U[0..2]``.

Every node is classified by what it depends on, and the kernel is printed as three loops over
a block of pixels (each vectorised over the pixels by gcc):

1. *pre*: the pixel-level nodes (no light dependence: ``v``, the material terms, ``n·v`` …)
   that the light loop reads are computed once per pixel into small stack arrays ``bd*``;
2. *light loop*, ``for (j = 0; j < L; ++j)``: the light-dependent nodes; light-only nodes
   (``normalize(d)``) are hoisted above the pixel loop. The forward accumulates the radiance;
   the backward runs the reverse graph of the body (:func:`.trace.reverse` stopped at the
   pixel-level boundary) and accumulates the adjoint of every boundary node across lights
   (``ga*``);
3. *post*: the forward stores the sum; the backward propagates the accumulated boundary
   adjoints back to the per-pixel inputs (a second :func:`.trace.reverse` over the
   pixel-level part, recomputed) and writes each input's gradient once.

With ``uniform_grad`` the backward also differentiates w.r.t. the uniforms: the adjoint of each
light's six uniforms (from the loop body's reverse pass) and of the camera (from the post
pass) are summed over each block's pixels (:attr:`.light_loop.LoopSchedule.sums`); the caller
adds the blocks' partial sums.

So each pixel's material is read once per pass, the per-light work is only what depends on the
light, memory is flat in the number of lights, and the light count is a runtime argument (no
rebuild per count). Nothing here knows a derivative rule or a formula.

Kernel ABI (same symbols and arguments as the principled kernels, see :mod:`.codegen_c`):

* ``tb_fwd(n, in, P, out, nthreads)``; ``tb_bwd(n, in, P, go, gout, nthreads)``;
* ``in[k]`` the per-pixel tensors of ``spec.tensors``, ``in[T]`` the uniform row
  ``[C (3), point lights Lp × (q, I), directional lights Ld × (d, E)]``;
* ``P`` the runtime Python floats of ``spec.floats``, then ``Lp`` and ``Ld``;
* ``out`` ``(n, 3)`` contiguous; ``go`` ``(n, 3)`` lane-dense, or one colour / one value for
  all pixels (``spec.go_mode`` ``"b1"`` / ``"b0"``: the gradient of a sum is read in place);
  ``gout[k]`` a lane-dense ``(n, C_k)`` gradient; with ``uniform_grad``, ``gout[T]`` the
  uniforms' partial gradients, double ``(ceil(n / BLOCK), 3 + 6 (Lp + Ld))``, zero-filled by
  the caller (block ``b``'s row: the sum over its pixels).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from torchbrdf.brdf import formula
from torchbrdf.brdf.formula import SCALAR_PARAMS
from torchbrdf.kernels.codegen_c import lane_index
from torchbrdf.kernels.light_loop import Layout, LightLoop, LoopSchedule, flags, print_c, print_triton
from torchbrdf.kernels.trace import Graph, Node, TraceOps, Vec3, reverse

__all__ = ["ShadeSpec", "LoopSchedule", "schedule", "generate", "generate_triton", "LIGHT_KINDS",
           "LIGHT_STRIDE", "FAMILIES"]

LIGHT_KINDS = ("point", "directional")
LIGHT_STRIDE = 6  # uniforms per light: position/direction (3), intensity/irradiance (3)
CAMERA = 3  # uniforms before the lights: the camera position
# Pixels per block: the pre-loop's boundary values and the backward's adjoint accumulators
# live in stack arrays of this length (~60 arrays × 128 × 8 B ≈ 60 KiB, L2-resident).
BLOCK = 128
_FORMULA_FUNCS = ("normalize", "view_direction", "point_light", "directional_light", "principled", "svbrdf_ggx")
FAMILIES = formula.LOOP_BRDFS  # the BRDFs it traces, by name


def formula_token() -> tuple:
    """Identity of the traced formula functions (part of the in-process kernel key, so that a
    replaced formula function — e.g. patched in a test — is traced anew)."""
    return tuple(id(getattr(formula, f)) for f in _FORMULA_FUNCS)


class ShadeSpec:
    """Everything that changes the generated shading code.

    ``tensors``: ``(name, mode, C)`` per per-pixel input (``pos, n`` first, then ``x, y`` when
    ``frame``, ``base_color`` and the scalar maps); ``floats``: names of the material
    parameters passed as runtime floats; ``lights``: the light kinds present (each gets its
    loop); ``grad_mask``: backward, the inputs whose gradient is wanted; ``normalize_n``: ``n`` is the
    raw normal, normalised in the kernel; ``go_mode``: the output gradient's layout;
    ``uniform_grad``: backward, also the gradient w.r.t. the uniform row (camera and lights);
    ``family``: the BRDF (:data:`FAMILIES`).
    """

    def __init__(
        self,
        ctype: str,
        tensors: Iterable[tuple[str, str, int]],
        floats: Iterable[str],
        active: Iterable[str],
        need_tint: bool,
        frame: bool,
        lights: Iterable[str],
        grad_mask: Iterable[int] = (),
        normalize_n: bool = False,
        go_mode: str = "full",
        uniform_grad: bool = False,
        family: str = "principled",
    ) -> None:
        if family not in FAMILIES:
            raise ValueError(f"family: expected one of {FAMILIES}, got {family!r}")
        self.ctype = ctype
        self.family = family
        self.hi_double = ctype == "float"
        self.tensors = tuple(tensors)
        self.floats = tuple(floats)
        self.active = tuple(active)
        self.need_tint = bool(need_tint)
        self.frame = bool(frame)
        self.lights = tuple(k for k in LIGHT_KINDS if k in lights)
        self.grad_mask = tuple(grad_mask)
        self.go_mode = go_mode
        self.normalize_n = bool(normalize_n)
        self.uniform_grad = bool(uniform_grad)
        self.written: tuple[int, ...] = ()  # set by the backward's generator

    def key(self, backward: bool | str) -> tuple[Any, ...]:
        """The in-process cache key of the forward (``backward`` false) or backward kernel."""
        base = (
            "shade",
            self.ctype,
            self.tensors,
            self.floats,
            self.active,
            self.need_tint,
            self.frame,
            self.lights,
            self.normalize_n,
            self.family,
            formula_token(),
        )
        return base + (("bwd", self.grad_mask, self.go_mode, self.uniform_grad) if backward else ("fwd",))

    def generate(self, kind: str) -> str:
        return generate(self, kind)


def _in(role: str, kind="r", grad=False, **attr) -> Node:
    """An input node; ``role``: ``px`` (per-pixel load ``k``, channel ``c``), ``go`` (output
    gradient), ``cam`` (camera), ``light`` (the current light's uniform ``c``) or ``acc`` (a
    value accumulated over the light loop, read after it)."""
    return Node("in", (), kind, {"role": role, **attr}, grad=grad)


def _trace(spec: ShadeSpec):
    """Trace the shading formula. Returns ``(graph, loads, {light kind: [3 output nodes]},
    camera nodes, {light kind: its 6 uniform nodes})``."""
    g = Graph()
    with g:
        ops = TraceOps(spec.hi_double)
        inp: dict[str, Node | Vec3 | None] = {}
        loads: list[Node] = []
        for k, (name, mode, C) in enumerate(spec.tensors):
            chans = [_in("px", grad=True, k=k, c=c) for c in range(C)]
            loads += chans
            inp[name] = Vec3(chans) if C == 3 else chans[0]
        for j, name in enumerate(spec.floats):
            inp[name] = Node("P", (), "p", j)
        inp.setdefault("x", None)
        inp.setdefault("y", None)
        for name in SCALAR_PARAMS:
            inp.setdefault(name, None)
        pos = inp.pop("pos")
        if spec.normalize_n:  # the raw normal: normalised per pixel, outside the light loop
            inp["n"] = formula.normalize(ops, inp["n"])
        n = inp["n"]
        cam = Vec3(_in("cam", grad=spec.uniform_grad, c=c) for c in range(3))
        inp["v"] = formula.view_direction(ops, cam, pos)

        family = getattr(formula, spec.family)

        def brdf(l):
            return family(ops, {**inp, "l": l}, spec.active, spec.need_tint, spec.frame)

        outs = {}
        uniforms = {}
        for kind in spec.lights:
            u = [_in("light", grad=spec.uniform_grad, c=c) for c in range(LIGHT_STRIDE)]
            uniforms[kind] = u
            a, b = Vec3(u[:3]), Vec3(u[3:])
            if kind == "point":
                out = formula.point_light(ops, pos, n, a, b, brdf)
            else:
                out = formula.directional_light(ops, n, a, b, brdf)
            outs[kind] = list(out.c)
    return g, loads, outs, list(cam.c), uniforms


def schedule(spec: ShadeSpec, kind: str) -> LoopSchedule:
    """Trace the formula and build the forward (``"fwd"``) or backward (``"bwd"``) schedule."""
    g, loads, outs, cam, uniforms = _trace(spec)
    accs: dict[str, list[tuple[tuple[Any, ...], Node]]]
    post: list[tuple[tuple[Any, ...], Node | None]]
    with g:
        if kind == "fwd":
            accs = {lk: [(("out", c), o) for c, o in enumerate(outs[lk])] for lk in spec.lights}
            acc_kind = {("out", c): "r" for c in range(3)}
            post = [(("out", c), _in("acc", key=("out", c))) for c in range(3)]
            return LoopSchedule(g, accs, acc_kind, post)
        if kind != "bwd":
            raise ValueError(kind)
        go = [_in("go", c=c) for c in range(3)]
        lit, px = flags(g)
        # The loop body's reverse pass stops at the pixel-level values (no light dependence):
        # their adjoints are summed over the lights and propagated further after the loop.
        stop = frozenset(i for i in px if i not in lit)
        byid = {nd.id: nd for nd in g.nodes}
        accs = {}
        sums: dict[str, list[tuple[tuple[Any, ...], Node | None]]] = {}
        bnd: set[int] = set()
        for lk in spec.lights:
            adj = reverse(g, outs[lk], go, stop=stop)
            accs[lk] = [(("adj", b), adj[b]) for b in sorted(stop) if b in adj]
            bnd |= {b for b in stop if b in adj}
            if spec.uniform_grad:  # this light's uniforms: summed over the pixels, per light
                sums[lk] = [(("light", c), adj.get(u.id)) for c, u in enumerate(uniforms[lk])]
        bnd_ids = sorted(bnd)
        acc_kind = {("adj", b): byid[b].kind for b in bnd_ids}
        seeds = [_in("acc", byid[b].kind, key=("adj", b)) for b in bnd_ids]
        adj2 = reverse(g, [byid[b] for b in bnd_ids], seeds)
        written: list[int] = []
        post = []
        for k, (name, mode, C) in enumerate(spec.tensors):
            if k not in spec.grad_mask or not any(nd.attr["k"] == k and nd.id in adj2 for nd in loads):
                continue  # no path to the output: None in autograd, as in eager
            written.append(k)
            for c in range(C):
                nd = next(x for x in loads if x.attr["k"] == k and x.attr["c"] == c)
                post.append((("grad", k, c), adj2.get(nd.id)))
        post_sums = [(("cam", c), adj2.get(nd.id)) for c, nd in enumerate(cam)] if spec.uniform_grad else []
        return LoopSchedule(g, accs, acc_kind, post, written, sums=sums, post_sums=post_sums)


def generate(spec: ShadeSpec, kind: str) -> str:
    """C source of the forward (``"fwd"``) or backward (``"bwd"``) shading kernel.

    For ``"bwd"`` it sets ``spec.written``: the inputs whose gradient the kernel writes.
    """
    sch = schedule(spec, kind)
    spec.written = sch.written
    T = len(spec.tensors)
    F = len(spec.floats)
    decl = [f"const R* __restrict p{k} = (const R*)in[{k}];" for k in range(T)]
    decl += [
        f"const R* __restrict U = (const R*)in[{T}];",
        f"const long Lp = (long)P[{F}];",
        f"const long Ld = (long)P[{F + 1}];",
    ]
    if kind == "fwd":
        sig = "void tb_fwd(long n, void** in, const double* P, R* __restrict out, int nthreads)"
    else:
        decl += [f"R* __restrict gp{k} = (R*)gout[{k}];" for k in sch.written]
        if spec.uniform_grad:
            decl += [f"double* __restrict gU = (double*)gout[{T}];",
                     f"const long W = {CAMERA} + {LIGHT_STRIDE} * (Lp + Ld);"]
        sig = (
            "void tb_bwd(long n, void** in, const double* P, const R* __restrict go, void** gout, "
            "int nthreads)"
        )
    return print_c(spec.ctype, sch, _layout(spec), decl, sig)


def generate_triton(spec: ShadeSpec, kind: str, wide: bool = False) -> str:
    """Triton source of the forward (``"fwd"``) or backward (``"bwd"``) shading kernel.

    ``tb_fwd(n, P, U, x0 .. x{T-1}, out, Lp, Ld, BLOCK)``;
    ``tb_bwd(n, P, U, x0 .. x{T-1}, go, g{k} for k in spec.written[, gU], Lp, Ld, BLOCK)``: ``x{k}``
    the per-pixel inputs (``spec.tensors``), ``U`` the segment's uniform row (camera, then the
    lights, as in C), ``P`` the runtime floats (float64), ``Lp`` / ``Ld`` the light counts,
    ``out`` / ``g{k}`` lane-dense ``(n, 3)`` / ``(n, C_k)``, ``go`` in ``spec.go_mode``, ``gU``
    (with ``spec.uniform_grad``) the uniforms' per-block partial gradients as in C. Sets
    ``spec.written`` for ``"bwd"``.
    """
    sch = schedule(spec, kind)
    spec.written = sch.written
    args = [f"x{k}" for k in range(len(spec.tensors))]
    args += ["out"] if kind == "fwd" else ["go"] + [f"g{k}" for k in sch.written]
    args += ["gU"] if kind == "bwd" and spec.uniform_grad else []
    return print_triton(spec.ctype, sch, _layout(spec), f"tb_{kind}", args + ["Lp", "Ld"], wide)


def _tl_index(mode: str, C: int, c: int) -> str:
    """A Triton load's address offset and mask for a per-pixel value in ``mode``."""
    if mode == "full":
        return f"i * {C} + {c}, mask=m, other=0.0" if C > 1 else "i, mask=m, other=0.0"
    return f"{c}" if mode == "b1" else "0"


def _layout(spec: ShadeSpec) -> Layout:
    """The shading kernels' loads and stores (C and Triton)."""

    def load_c(a: dict) -> str:
        role = a["role"]
        if role == "px":
            _, mode, C = spec.tensors[a["k"]]
            return f"p{a['k']}[{lane_index(mode, C, a['c'])}]"
        if role == "go":
            return f"go[{lane_index(spec.go_mode, 3, a['c'])}]"
        return f"U[{a['c']}]" if role == "cam" else f"u[{a['c']}]"

    def load_t(a: dict) -> str:
        role = a["role"]
        if role == "px":
            _, mode, C = spec.tensors[a["k"]]
            return f"tl.load(x{a['k']} + {_tl_index(mode, C, a['c'])})"
        if role == "go":
            return f"tl.load(go + {_tl_index(spec.go_mode, 3, a['c'])})"
        return f"tl.load(U + {a['c']})" if role == "cam" else f"tl.load(u + {a['c']})"

    def store_c(store: tuple) -> str:
        if store[0] == "out":
            return f"out[i * 3 + {store[1]}]"
        _, k, c = store
        return f"gp{k}[i * {spec.tensors[k][2]} + {c}]"

    def store_t(store: tuple) -> str:
        if store[0] == "out":
            return f"out + (i * 3 + {store[1]})"
        _, k, c = store
        return f"g{k} + (i * {spec.tensors[k][2]} + {c})"

    def sum_offset(key: tuple, light: str | None) -> str:
        # the uniform row's layout: camera, then LIGHT_STRIDE per light
        return f"{key[1]}" if key[0] == "cam" else f"{CAMERA} + {LIGHT_STRIDE} * {light} + {key[1]}"

    def sum_c(key: tuple, light: str | None) -> str:
        return f"gU[blk * W + {sum_offset(key, light)}]"

    def sum_t(key: tuple, light: str | None) -> str:
        return f"gU + (blk * ({CAMERA} + {LIGHT_STRIDE} * (Lp + Ld)) + {sum_offset(key, light)})"

    loops = [LightLoop("point", "0", "Lp"), LightLoop("directional", "Lp", "Ld")]
    return Layout([lp for lp in loops if lp.name in spec.lights], load_c, store_c, load_t, store_t,
                  skip=CAMERA, stride=LIGHT_STRIDE, block=BLOCK, sum_c=sum_c, sum_triton=sum_t)


