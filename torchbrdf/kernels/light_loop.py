"""Light-loop kernels: a traced per-pixel graph printed as pre-loop, loop over lights, post-loop.

A light-loop kernel (fused shading, :mod:`.codegen_shade`; the recovery's normal equations,
:mod:`.codegen_normal_eq`) sums per-light terms per pixel. Its graph's nodes are classified by
what they depend on (:func:`flags`): input roles that change with the light (``lit_roles``:
the light's uniforms, a per-pixel-per-light observation) and roles that change with the pixel
(``px_roles``). The kernel is printed in three phases per block of pixels:

1. *pre*: the pixel-level nodes the loop reads (no light dependence), once per pixel;
2. *light loop* ``for j in lights``: the light-dependent nodes (those with no pixel dependence
   once per light), each root added into its accumulator;
3. *post*: nodes over the accumulated values (read through ``acc`` inputs), stored.

A value can also be *summed over the pixels* of a block (``sums``, per light inside the loop;
``post_sums`` after it): each block stores its own partial sum (summed in double, in lane
order) and the caller adds the blocks' partials, so the result does not depend on the thread
count or the schedule (no atomics).

A :class:`LoopSchedule` says what is accumulated and stored; :class:`Layout` how a kernel's
loads and stores are addressed. :func:`print_c` prints C (OpenMP over blocks, the lane loops
vectorised by gcc; the pre-loop's values in stack arrays), :func:`print_triton` a Triton
program per block (the loop a ``for`` over the lights with loop-carried accumulators). Nothing
here knows the formula or a derivative rule.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from torchbrdf.kernels.codegen_c import CHUNK_BLOCKS, EXP2_PRELUDE, PRELUDE, Emitter, lit
from torchbrdf.kernels.trace import Graph, Node, live_order

__all__ = ["LoopSchedule", "Layout", "LightLoop", "flags", "loop_nodes", "acc_input", "print_c",
           "print_triton"]


class LoopSchedule:
    """A light-loop kernel, independent of the language it is printed in.

    * ``graph``: all nodes;
    * ``accs``: per light loop (by name), ``[(key, node)]``: ``node`` is added into accumulator
      ``key`` once per light; ``acc_kind[key]`` its value kind (``'r'`` or ``'d'``);
    * ``post``: ``[(store, node or None)]`` after the loops (``None``: zero); nodes there read
      accumulators through :func:`acc_input` nodes;
    * ``written``: inputs whose gradient a backward writes;
    * ``stores``: per light loop (by name), ``[(store, node)]``: ``node`` is stored once per
      pixel and light, inside the loop (the layout's store address may use the light ``j``);
    * ``sums``: per light loop (by name), ``[(key, node or None)]``: ``node`` summed over the
      block's pixels, once per light, stored at ``Layout.sum_c/sum_triton(key, light)``;
    * ``post_sums``: ``[(key, node or None)]``: the same after the loops (light ``None``).
    """

    def __init__(
        self,
        graph: Graph,
        accs: dict[str, list[tuple[tuple[Any, ...], Node]]],
        acc_kind: dict[tuple[Any, ...], str],
        post: list[tuple[tuple[Any, ...], Node | None]],
        written: Iterable[int] = (),
        stores: dict[str, list[tuple[tuple[Any, ...], Node]]] | None = None,
        sums: dict[str, list[tuple[tuple[Any, ...], Node | None]]] | None = None,
        post_sums: list[tuple[tuple[Any, ...], Node | None]] | None = None,
    ) -> None:
        self.graph, self.accs, self.acc_kind, self.post, self.written = (
            graph,
            accs,
            acc_kind,
            post,
            tuple(written),
        )
        self.stores = dict(stores or {})
        self.sums = dict(sums or {})
        self.post_sums = list(post_sums or [])


def acc_input(key: tuple[Any, ...], kind: str = "r") -> Node:
    """The node reading accumulator ``key`` after the light loops (in the graph being built)."""
    return Node("in", (), kind, {"role": "acc", "key": key})


@dataclass
class LightLoop:
    """One loop over lights: ``name`` (its :attr:`LoopSchedule.accs` entry), the first light's
    index and the light count, as expressions of the kernel's arguments (C and Triton alike)."""

    name: str
    first: str
    count: str


@dataclass
class Layout:
    """How one kernel addresses its data, per language.

    ``load_c(attr)`` / ``load_triton(attr)``: an ``in`` node's load (``i`` the pixel, ``j`` the
    light, ``u`` the current light's uniforms); ``store_c(store)`` / ``store_triton(store)``:
    the address a post-loop value is stored to; ``lit_roles`` / ``px_roles``: the input roles
    that depend on the light / on the pixel; ``uniforms``: the expression of the uniform table,
    ``stride`` uniforms per light after ``skip`` leading ones. ``sum_c(key, light)`` /
    ``sum_triton(key, light)``: where a block's partial sum goes (``blk`` the block, ``light``
    the light's index expression, None after the loops). ``carry_loads``: the per-pixel loads
    the light loops read are copied once per block into lane-contiguous arrays, as the pre-loop's
    values are (worth it where a pixel's channels are interleaved: the loop's loads are then
    contiguous instead of strided, once per pixel instead of once per pixel-light); otherwise
    they are re-read from their tensors inside the loops.
    """

    loops: Sequence[LightLoop]
    load_c: Callable[[dict], str]
    store_c: Callable[[tuple], str]
    load_triton: Callable[[dict], str] | None = None
    store_triton: Callable[[tuple], str] | None = None
    lit_roles: tuple[str, ...] = ("light",)
    px_roles: tuple[str, ...] = ("px", "go")
    skip: int = 3
    stride: int = 6
    block: int = 128
    extra: dict = field(default_factory=dict)
    sum_c: Callable[[tuple, str | None], str] | None = None
    sum_triton: Callable[[tuple, str | None], str] | None = None
    carry_loads: bool = False


def flags(g: Graph, lit_roles: Iterable[str] = ("light",), px_roles: Iterable[str] = ("px", "go")
          ) -> tuple[set[int], set[int]]:
    """Ids of the nodes that depend on a light (``lit``) and on a pixel (``px``)."""
    lit_r, px_r = set(lit_roles), set(px_roles)
    lit: set[int] = set()
    px: set[int] = set()
    for nd in g.nodes:
        if nd.op == "in":
            role = nd.attr["role"]
            if role in lit_r:
                lit.add(nd.id)
            if role in px_r:
                px.add(nd.id)
            continue
        for a in nd.args:
            if isinstance(a, Node):
                if a.id in lit:
                    lit.add(nd.id)
                if a.id in px:
                    px.add(nd.id)
    return lit, px


def _is_boundary(nd: Node, lit, px, carry_loads: bool) -> bool:
    """A pixel-level value the light loop reads from the pre-loop (masks are printed inline, so
    never carried; loads only with ``carry_loads``, else re-read from their tensor)."""
    return nd.id in px and nd.id not in lit and (carry_loads or nd.op != "in") and nd.kind != "b"


def loop_nodes(roots: Iterable[Node | float | None], lit: set[int], px: set[int], carry_loads: bool = False
               ) -> tuple[set[int], set[int]]:
    """Nodes of a light-loop body (ids) and the boundary nodes it reads (ids); ``carry_loads``
    as for :class:`Layout`."""
    body: set[int] = set()
    bnd: set[int] = set()
    stack = [r for r in roots if isinstance(r, Node)]
    while stack:
        nd = stack.pop()
        if nd.id in body or nd.id in bnd:
            continue
        if _is_boundary(nd, lit, px, carry_loads):
            bnd.add(nd.id)
            continue
        body.add(nd.id)
        stack.extend(a for a in nd.args if isinstance(a, Node))
    return body, bnd


def _acc_name(key) -> str:
    """A C/Python identifier for accumulator ``key`` (a tuple of a tag and ints)."""
    return "a_" + "_".join(str(k) for k in key)


def _phases(sch: LoopSchedule, lay: Layout):
    """``(lit, px, per loop (body ids, boundary ids), boundary ids of all loops)``."""
    lit, px = flags(sch.graph, lay.lit_roles, lay.px_roles)
    loops = {}
    bnd_all: set[int] = set()
    for lp in lay.loops:
        roots = [nd for _, nd in sch.accs.get(lp.name, []) + sch.stores.get(lp.name, [])]
        roots += [nd for _, nd in sch.sums.get(lp.name, []) if nd is not None]
        body, bnd = loop_nodes(roots, lit, px, lay.carry_loads)
        loops[lp.name] = (body, bnd)
        bnd_all |= bnd
    return lit, px, loops, bnd_all


# ---------------------------------------------------------------------------------------------
# C
# ---------------------------------------------------------------------------------------------

def print_c(ctype: str, sch: LoopSchedule, lay: Layout, decl: Sequence[str], sig: str) -> str:
    """C source of a light-loop kernel: ``sig`` (its declaration), ``decl`` (statements before
    the pixel loop; they define ``n``'s data pointers and the uniform table ``U``)."""
    g = sch.graph

    def load(attr):
        if attr["role"] == "acc":
            return f"{_acc_name(attr['key'])}[i - b0]"
        return lay.load_c(attr)

    em = Emitter(ctype, load)
    byid = {nd.id: nd for nd in g.nodes}
    lit, px, phases, bnd_all = _phases(sch, lay)
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

    loops: list[str] = []
    for lp in lay.loops:
        if lp.name not in sch.accs:
            continue
        body, bnd = phases[lp.name]
        names: dict = {}
        scal: list[str] = []
        lane: list[str] = []
        order = [nd for nd in g.nodes if nd.id in body or nd.id in bnd]
        emit([nd for nd in order if nd.id in body and nd.id not in px], names, scal)
        emit([nd for nd in order if nd.id in bnd or nd.id in px], names, lane,
             reads={b: f"bd{b}[i - b0]" for b in bnd})
        lane += [f"{_acc_name(key)}[i - b0] += {names[nd.id]};" for key, nd in sch.accs[lp.name]]
        lane += [f"{lay.store_c(key)} = {names[nd.id]};" for key, nd in sch.stores.get(lp.name, [])]
        sums = [(key, nd) for key, nd in sch.sums.get(lp.name, []) if nd is not None]
        lane += [f"sm{q}[i - b0] = {names[nd.id]};" for q, (_, nd) in enumerate(sums)]
        loops += [
            f"    for (long j = 0; j < {lp.count}; ++j) {{",
            f"      const R* __restrict u = U + {lay.skip} + {lay.stride} * ({lp.first} + j);",
            *("      " + s for s in scal),
            "      #pragma GCC ivdep",
            "      for (long i = b0; i < b1; ++i) {",
            *("        " + s for s in lane),
            "      }",
            *("      " + s for s in _c_block_sums(lay, sums, f"({lp.first} + j)")),
            "    }",
        ]

    pre_names: dict = {}
    pre: list[str] = []
    bnd_sorted = sorted(bnd_all)
    emit(live_order(g, [byid[b] for b in bnd_sorted]), pre_names, pre)
    pre += [f"bd{b}[i - b0] = {pre_names[b]};" for b in bnd_sorted]

    post_names: dict = {}
    post: list[str] = []
    post_sums = [(key, nd) for key, nd in sch.post_sums if nd is not None]
    emit(live_order(g, [nd for _, nd in sch.post + post_sums if isinstance(nd, Node)]), post_names, post)
    for store, val in sch.post:
        post.append(f"{lay.store_c(store)} = {post_names[val.id] if isinstance(val, Node) else '((R)0)'};")
    post += [f"sm{q}[i - b0] = {post_names[nd.id]};" for q, (_, nd) in enumerate(post_sums)]
    n_sm = max([len(post_sums)]
               + [sum(nd is not None for _, nd in sch.sums.get(lp.name, [])) for lp in lay.loops])

    B = lay.block
    src = [
        PRELUDE + (EXP2_PRELUDE if any(nd.op == "exp2" for nd in g.nodes) else ""),
        f"typedef {ctype} R;",
        "#define SQRT_R(x) " + ("__builtin_sqrtf(x)" if ctype == "float" else "__builtin_sqrt(x)"),
        sig + " {",
        *("  " + d for d in decl),
        f"  #pragma omp parallel for schedule(dynamic, {CHUNK_BLOCKS}) num_threads(nthreads)",
        f"  for (long b0 = 0; b0 < n; b0 += {B}) {{",
        f"    const long b1 = b0 + {B} < n ? b0 + {B} : n;",
        *(f"    {'R' if byid[b].kind == 'r' else 'double'} bd{b}[{B}];" for b in bnd_sorted),
        *(f"    {t} {name}[{B}];" for t, name in acc_arrays),
        *(f"    double sm{q}[{B}];" for q in range(n_sm)),
        *([f"    const long blk = b0 / {B};"] if n_sm else []),
        *(f"    for (long i = 0; i < {B}; ++i) {name}[i] = 0;" for _, name in acc_arrays),
        "    #pragma GCC ivdep",
        "    for (long i = b0; i < b1; ++i) {",
        *("      " + s for s in pre),
        "    }",
        *loops,
        "    #pragma GCC ivdep",
        "    for (long i = b0; i < b1; ++i) {",
        *("      " + s for s in post),
        "    }",
        *("    " + s for s in _c_block_sums(lay, post_sums, None)),
        "  }",
        "}",
    ]
    return "\n".join(src) + "\n"


def _c_block_sums(lay: Layout, sums: Sequence[tuple[tuple, Node]], light: str | None) -> list[str]:
    """C: add up the block's lanes of each summed value (``sm{q}``, in lane order, in double)
    and store the block's partial sums."""
    if not sums:
        return []
    if lay.sum_c is None:
        raise ValueError("print_c: the schedule sums over pixels but the layout has no sum_c")
    acc = ", ".join(f"t{q} = 0" for q in range(len(sums)))
    return [
        f"{{ double {acc};",
        "  for (long i = b0; i < b1; ++i) {",
        *(f"    t{q} += sm{q}[i - b0];" for q in range(len(sums))),
        "  }",
        *(f"  {lay.sum_c(key, light)} = t{q};" for q, (key, _) in enumerate(sums)),
        "}",
    ]


def _namer(names):
    """Name of a node (or a literal for a Python number) in the current phase."""

    def v(nd):
        return names[nd.id] if isinstance(nd, Node) else f"((R){lit(nd)})"

    return v


# ---------------------------------------------------------------------------------------------
# Triton
# ---------------------------------------------------------------------------------------------

def print_triton(ctype: str, sch: LoopSchedule, lay: Layout, name: str, args: Sequence[str],
                 wide: bool = False) -> str:
    """Triton source of a light-loop kernel ``name(n, P, U, *args, BLOCK)``.

    One program per ``BLOCK`` of pixels: the pre-loop values are ``[BLOCK]`` tensors, each
    light loop is ``for j in range(first, first + count)`` whose accumulators are loop-carried
    ``[BLOCK]`` tensors, the light's uniforms scalar loads from ``U``. ``wide``: 64-bit pixel
    indices.
    """
    from torchbrdf.kernels.codegen_triton import PRELUDE as TPRELUDE
    from torchbrdf.kernels.codegen_triton import Printer
    from torchbrdf.kernels.codegen_triton import lit as tlit

    if lay.load_triton is None or lay.store_triton is None:
        raise ValueError("print_triton: the layout has no Triton loads/stores")
    load_t, store_t = lay.load_triton, lay.store_triton
    g = sch.graph
    pr = Printer(ctype)

    def load(nd: Node) -> str:
        if nd.attr["role"] == "acc":
            return _acc_name(nd.attr["key"])
        return load_t(nd.attr)

    pr.load = load  # type: ignore[method-assign]
    byid = {nd.id: nd for nd in g.nodes}
    lit, px, phases, bnd_all = _phases(sch, lay)

    def v_of(names):
        def v(nd):
            return names[nd.id] if isinstance(nd, Node) else f"tl.full([BLOCK], {tlit(nd)}, {pr.DT})"
        return v

    def emit(nodes, names, lines, done=()):
        for nd in nodes:
            if nd.id in done:
                continue
            names[nd.id] = f"v{nd.id}"
            lines.append(f"v{nd.id} = {pr.expr(nd, v_of(names))}")

    names: dict = {}
    pre: list[str] = []
    emit(live_order(g, [byid[b] for b in sorted(bnd_all)]), names, pre)
    loops: list[str] = []
    # (tl.full, a builtin: tl.zeros is a jit function of the standard library, which the
    # interpreter runs only if it was imported under TRITON_INTERPRET)
    inits = [f"{_acc_name(key)} = tl.full([BLOCK], 0.0, {pr.ty(k)})" for key, k in sch.acc_kind.items()]
    for lp in lay.loops:
        if lp.name not in sch.accs:
            continue
        body, bnd = phases[lp.name]
        lnames = dict(names)  # the pre-loop values are read by name
        lines: list[str] = []
        emit([nd for nd in g.nodes if nd.id in body], lnames, lines, done=set(names))
        lines += [f"{_acc_name(key)} += {lnames[nd.id]}" for key, nd in sch.accs[lp.name]]
        lines += [f"tl.store({store_t(key)}, tl.broadcast_to({lnames[nd.id]}, [BLOCK]), mask=m)"
                  for key, nd in sch.stores.get(lp.name, [])]
        lines += [_triton_block_sum(lay, key, lnames[nd.id], "j")
                  for key, nd in sch.sums.get(lp.name, []) if nd is not None]
        loops += [
            f"for j in range({lp.first}, {lp.first} + {lp.count}):",
            f"    u = U + {lay.skip} + {lay.stride} * j",
            *("    " + s for s in lines),
        ]
    pnames: dict = {}
    post: list[str] = []
    post_sums = [(key, nd) for key, nd in sch.post_sums if nd is not None]
    emit(live_order(g, [nd for _, nd in sch.post + post_sums if isinstance(nd, Node)]), pnames, post)
    for store, val in sch.post:
        value = pnames[val.id] if isinstance(val, Node) else f"tl.full([BLOCK], 0.0, {pr.DT})"
        post.append(f"tl.store({store_t(store)}, tl.broadcast_to({value}, [BLOCK]), mask=m)")
    post += [_triton_block_sum(lay, key, pnames[nd.id], None) for key, nd in post_sums]
    pid = "tl.program_id(0).to(tl.int64)" if wide else "tl.program_id(0)"
    summed = bool(post_sums) or any(nd is not None for sums in sch.sums.values() for _, nd in sums)
    if summed:
        pre.insert(0, f"blk = {pid}")
    src = [
        TPRELUDE,
        *([_TRITON_ADD] if summed else []),
        "@triton.jit",
        f"def {name}(n, P, U, {', '.join(args)}, BLOCK: tl.constexpr):",
        f"    i = {pid} * BLOCK + tl.arange(0, BLOCK)",
        "    m = i < n",
        *("    " + s for s in pre + inits + loops + post),
    ]
    return "\n".join(src) + "\n"


# The combine function of the block sums: tl.reduce is a builtin, while tl.sum is a jit function
# of Triton's standard library, which the interpreter runs only if imported under TRITON_INTERPRET.
_TRITON_ADD = """@triton.jit
def _tb_add(a, b):
    return a + b

"""


def _triton_block_sum(lay: Layout, key: tuple, value: str, light: str | None) -> str:
    """Triton: store the block's sum of ``value`` over its pixels (masked lanes are 0; double)."""
    if lay.sum_triton is None:
        raise ValueError("print_triton: the schedule sums over pixels but the layout has no sum_triton")
    lanes = f"tl.where(m, tl.broadcast_to({value}, [BLOCK]).to(tl.float64), 0.0)"
    return f"tl.store({lay.sum_triton(key, light)}, tl.reduce({lanes}, 0, _tb_add))"
