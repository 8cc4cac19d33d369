"""C code generation for fused shading: geometry, principled BRDF and the sum over lights in one loop.

:func:`generate` traces :func:`torchbrdf.brdf.formula.view_direction` and the per-light terms
:func:`~torchbrdf.brdf.formula.point_light` / :func:`~torchbrdf.brdf.formula.directional_light`
(with :func:`~torchbrdf.brdf.formula.principled` as the BRDF) into ONE graph whose inputs are
of three kinds:

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
  ``gout[k]`` a lane-dense ``(n, C_k)`` gradient.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from torchbrdf.brdf import formula
from torchbrdf.brdf.formula import SCALAR_PARAMS
from torchbrdf.kernels.codegen_c import CHUNK_BLOCKS, PRELUDE, Emitter, lane_index, lit
from torchbrdf.kernels.trace import Graph, Node, TraceOps, Vec3, live_order, reverse

__all__ = ["ShadeSpec", "LoopSchedule", "schedule", "generate", "LIGHT_KINDS", "LIGHT_STRIDE"]

LIGHT_KINDS = ("point", "directional")
LIGHT_STRIDE = 6  # uniforms per light: position/direction (3), intensity/irradiance (3)
CAMERA = 3  # uniforms before the lights: the camera position
# Pixels per block: the pre-loop's boundary values and the backward's adjoint accumulators
# live in stack arrays of this length (~60 arrays × 128 × 8 B ≈ 60 KiB, L2-resident).
BLOCK = 128
_FORMULA_FUNCS = ("normalize", "view_direction", "point_light", "directional_light", "principled")


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
    raw normal, normalised in the kernel; ``go_mode``: the output gradient's layout.
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
    ) -> None:
        self.ctype = ctype
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
            formula_token(),
        )
        return base + (("bwd", self.grad_mask, self.go_mode) if backward else ("fwd",))

    def generate(self, kind: str) -> str:
        return generate(self, kind)


def _in(role: str, kind="r", grad=False, **attr) -> Node:
    """An input node; ``role``: ``px`` (per-pixel load ``k``, channel ``c``), ``go`` (output
    gradient), ``cam`` (camera), ``light`` (the current light's uniform ``c``) or ``acc`` (a
    value accumulated over the light loop, read after it)."""
    return Node("in", (), kind, {"role": role, **attr}, grad=grad)


def _trace(spec: ShadeSpec):
    """Trace the shading formula. Returns ``(graph, loads, {light kind: [3 output nodes]})``."""
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
        cam = Vec3(_in("cam", c=c) for c in range(3))
        inp["v"] = formula.view_direction(ops, cam, pos)

        def brdf(l):
            return formula.principled(ops, {**inp, "l": l}, spec.active, spec.need_tint, spec.frame)

        outs = {}
        for kind in spec.lights:
            u = [_in("light", c=c) for c in range(LIGHT_STRIDE)]
            a, b = Vec3(u[:3]), Vec3(u[3:])
            if kind == "point":
                out = formula.point_light(ops, pos, n, a, b, brdf)
            else:
                out = formula.directional_light(ops, n, a, b, brdf)
            outs[kind] = list(out.c)
    return g, loads, outs


def _flags(g: Graph):
    """Ids of the nodes that depend on a light uniform (``lit``) and on a per-pixel value (``px``)."""
    lit, px = set(), set()
    for nd in g.nodes:
        if nd.op == "in":
            role = nd.attr["role"]
            if role == "light":
                lit.add(nd.id)
            if role in ("px", "go"):
                px.add(nd.id)
            continue
        for a in nd.args:
            if isinstance(a, Node):
                if a.id in lit:
                    lit.add(nd.id)
                if a.id in px:
                    px.add(nd.id)
    return lit, px


def _is_boundary(nd: Node, lit, px) -> bool:
    """A pixel-level value the light loop reads from the pre-loop's array (loads are re-read
    from their tensor and masks are printed inline, so neither needs an array)."""
    return nd.id in px and nd.id not in lit and nd.op != "in" and nd.kind != "b"


def _loop_nodes(roots, lit, px):
    """Nodes of a light-loop body (ids) and the boundary nodes it reads (ids)."""
    body, bnd = set(), set()
    stack = [r for r in roots if isinstance(r, Node)]
    while stack:
        nd = stack.pop()
        if nd.id in body or nd.id in bnd:
            continue
        if _is_boundary(nd, lit, px):
            bnd.add(nd.id)
            continue
        body.add(nd.id)
        stack.extend(a for a in nd.args if isinstance(a, Node))
    return body, bnd


class LoopSchedule:
    """A light-loop kernel, independent of the language it is printed in.

    * ``graph``: all nodes (forward, and for the backward both reverse passes);
    * ``accs``: per light kind, ``[(key, node)]``: ``node`` is added into accumulator ``key``
      once per light (keys: ``("out", c)`` radiance channel, ``("adj", id)`` the adjoint of
      pixel-level node ``id``); ``acc_kind[key]`` its value kind;
    * ``post``: ``[(store, node or None)]`` after the loop, ``store`` = ``("out", c)`` or
      ``("grad", k, c)`` (``None``: zero); nodes there read accumulators through ``acc`` inputs;
    * ``written``: inputs whose gradient the backward writes.

    An emitter classifies nodes with :func:`_flags` / :func:`_loop_nodes` (pre-loop, per-light
    scalars, light loop) and prints the three phases; see :func:`_print` for C.
    """

    def __init__(
        self,
        graph: Graph,
        accs: dict[str, list[tuple[tuple[Any, ...], Node]]],
        acc_kind: dict[tuple[Any, ...], str],
        post: list[tuple[tuple[Any, ...], Node | None]],
        written: Iterable[int] = (),
    ) -> None:
        self.graph, self.accs, self.acc_kind, self.post, self.written = (
            graph,
            accs,
            acc_kind,
            post,
            tuple(written),
        )


def schedule(spec: ShadeSpec, kind: str) -> LoopSchedule:
    """Trace the formula and build the forward (``"fwd"``) or backward (``"bwd"``) schedule."""
    g, loads, outs = _trace(spec)
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
        lit, px = _flags(g)
        # The loop body's reverse pass stops at the pixel-level values (no light dependence):
        # their adjoints are summed over the lights and propagated further after the loop.
        stop = frozenset(i for i in px if i not in lit)
        byid = {nd.id: nd for nd in g.nodes}
        accs = {}
        bnd: set[int] = set()
        for lk in spec.lights:
            adj = reverse(g, outs[lk], go, stop=stop)
            accs[lk] = [(("adj", b), adj[b]) for b in sorted(stop) if b in adj]
            bnd |= {b for b in stop if b in adj}
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
        return LoopSchedule(g, accs, acc_kind, post, written)


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
        sig = (
            "void tb_bwd(long n, void** in, const double* P, const R* __restrict go, void** gout, "
            "int nthreads)"
        )
    return _print(spec, sch, decl, sig)


def _acc_name(key) -> str:
    return f"ao{key[1]}" if key[0] == "out" else f"ga{key[1]}"


def _load_expr(spec: ShadeSpec, nd: Node) -> str:
    a = nd.attr
    role = a["role"]
    if role == "px":
        _, mode, C = spec.tensors[a["k"]]
        return f"p{a['k']}[{lane_index(mode, C, a['c'])}]"
    if role == "go":
        return f"go[{lane_index(spec.go_mode, 3, a['c'])}]"
    if role == "cam":
        return f"U[{a['c']}]"
    if role == "light":
        return f"u[{a['c']}]"
    return f"{_acc_name(a['key'])}[i - b0]"


def _store_expr(spec: ShadeSpec, store) -> str:
    if store[0] == "out":
        return f"out[i * 3 + {store[1]}]"
    _, k, c = store
    return f"gp{k}[i * {spec.tensors[k][2]} + {c}]"


def _print(spec: ShadeSpec, sch: LoopSchedule, decl, sig) -> str:
    """Print a schedule as C: pre-loop, light loops, post-loop over each block of pixels."""
    g, accs = sch.graph, sch.accs
    em = Emitter(spec.ctype, lambda attr: attr["load"])  # the loads are set on the nodes below
    lit, px = _flags(g)
    byid = {nd.id: nd for nd in g.nodes}
    for nd in g.nodes:
        if nd.op == "in":
            nd.attr["load"] = _load_expr(spec, nd)
    acc_arrays = [("R" if k == "r" else "double", _acc_name(key)) for key, k in sch.acc_kind.items()]

    def emit(nodes, names, lines, reads=None):
        reads = reads or {}
        for nd in nodes:
            if nd.id in reads:
                names[nd.id] = f"v{nd.id}"
                lines.append(f"const {em.t(nd.kind)} v{nd.id} = {reads[nd.id]};")
                continue
            v = _namer(names)
            if nd.kind == "b":  # masks are inlined (int mask variables stop gcc vectorising)
                names[nd.id] = f"({em.expr(nd, v)})"
                continue
            names[nd.id] = f"v{nd.id}"
            lines.append(f"const {em.t(nd.kind)} v{nd.id} = {em.expr(nd, v)};")

    # light loops
    loops, bnd_all = [], set()
    for lk in spec.lights:
        roots = [nd for _, nd in accs[lk]]
        body, bnd = _loop_nodes(roots, lit, px)
        bnd_all |= bnd
        names: dict = {}
        scal: list[str] = []
        lane: list[str] = []
        order = [nd for nd in g.nodes if nd.id in body or nd.id in bnd]
        emit([nd for nd in order if nd.id in body and nd.id not in px], names, scal)
        emit(
            [nd for nd in order if nd.id in bnd or nd.id in px],
            names,
            lane,
            reads={b: f"bd{b}[i - b0]" for b in bnd},
        )
        lane += [f"{_acc_name(key)}[i - b0] += {names[nd.id]};" for key, nd in accs[lk]]
        first = "0" if lk == "point" else "Lp"
        count = "Lp" if lk == "point" else "Ld"
        loops += [
            f"    for (long j = 0; j < {count}; ++j) {{",
            f"      const R* __restrict u = U + {CAMERA} + {LIGHT_STRIDE} * ({first} + j);",
            *("      " + s for s in scal),
            "      #pragma GCC ivdep",
            "      for (long i = b0; i < b1; ++i) {",
            *("        " + s for s in lane),
            "      }",
            "    }",
        ]

    # pre-loop: pixel-level values read by the light loops
    pre_names: dict = {}
    pre: list[str] = []
    bnd_sorted = sorted(bnd_all)
    emit(live_order(g, [byid[b] for b in bnd_sorted]), pre_names, pre)
    pre += [f"bd{b}[i - b0] = {pre_names[b]};" for b in bnd_sorted]

    # post-loop
    post_names: dict = {}
    post: list[str] = []
    roots = [nd for _, nd in sch.post if isinstance(nd, Node)]
    emit(live_order(g, roots), post_names, post)
    for store, val in sch.post:
        post.append(
            f"{_store_expr(spec, store)} = {post_names[val.id] if isinstance(val, Node) else '((R)0)'};"
        )

    def arr(kind_c, name):
        return f"    {kind_c} {name}[{BLOCK}];"

    src = [
        PRELUDE,
        f"typedef {spec.ctype} R;",
        "#define SQRT_R(x) " + ("__builtin_sqrtf(x)" if spec.ctype == "float" else "__builtin_sqrt(x)"),
        sig + " {",
        *("  " + d for d in decl),
        f"  #pragma omp parallel for schedule(dynamic, {CHUNK_BLOCKS}) num_threads(nthreads)",
        f"  for (long b0 = 0; b0 < n; b0 += {BLOCK}) {{",
        f"    const long b1 = b0 + {BLOCK} < n ? b0 + {BLOCK} : n;",
        *(arr("R" if byid[b].kind == "r" else "double", f"bd{b}") for b in bnd_sorted),
        *(arr(t, name) for t, name in acc_arrays),
        *(f"    for (long i = 0; i < {BLOCK}; ++i) {name}[i] = 0;" for _, name in acc_arrays),
        "    #pragma GCC ivdep",
        "    for (long i = b0; i < b1; ++i) {",
        *("      " + s for s in pre),
        "    }",
        *loops,
        "    #pragma GCC ivdep",
        "    for (long i = b0; i < b1; ++i) {",
        *("      " + s for s in post),
        "    }",
        "  }",
        "}",
    ]
    return "\n".join(src) + "\n"


def _namer(names):
    """Name of a node (or a literal for a Python number) in the current loop."""

    def v(nd):
        return names[nd.id] if isinstance(nd, Node) else f"((R){lit(nd)})"

    return v
