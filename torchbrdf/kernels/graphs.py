"""The kernel graphs of one kernel family, independent of any emitter.

:func:`build` traces the family's formula (:data:`torchbrdf.brdf.formula.FAMILIES`:
:func:`~torchbrdf.brdf.formula.principled`, or the recovery's
:func:`~torchbrdf.brdf.formula.capture_log_residual`) for a kernel spec
(``torchbrdf.kernels.fused.KernelSpec``) and applies the derivative transform a kernel needs.
The result names its loads and stores abstractly, so a C printer (:mod:`.codegen_c`) and a
Triton printer can print the same graph:

* load nodes (op ``in``), ``attr``: ``{"role": "x", "k", "c", "mode", "C"}`` — channel ``c`` of
  tensor input ``k`` (``mode`` 'full' lane-dense ``(n, C)``, 'b1' one ``C``-vector for all lanes,
  'b0' one value); ``{"role": "go", "c"}`` — the output gradient; ``{"role": "t", "j", "i", "k",
  "c", "mode", "C"}`` — channel ``c`` of tangent ``j`` of the ``i``-th input with a tangent
  (``spec.tangent_inputs[i] == k``);
* runtime floats: op ``P``, ``attr`` = index into the float parameters;
* stores ``(target, value)``: ``("out", c)``, ``("grad", k, c)`` (lane-dense ``(n, C_k)``),
  ``("tout", j, c)``; ``value`` is a node or a Python float.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from torchbrdf.brdf import formula
from torchbrdf.brdf.formula import SCALAR_PARAMS
from torchbrdf.kernels.trace import Graph, Node, TraceOps, Vec3, reverse, tangents

if TYPE_CHECKING:  # fused imports this module (through codegen_c) at run time
    from torchbrdf.kernels.fused import KernelSpec

__all__ = ["KernelGraph", "build"]


@dataclass
class KernelGraph:
    """One kernel: its graph, its stores and (backward) the inputs whose gradient it writes."""

    kind: str
    graph: Graph
    stores: list[tuple[tuple[Any, ...], Node | float]]
    written: tuple[int, ...] = ()


def _inputs(spec):
    """Formula inputs of one kernel family and the load nodes."""
    inp, loads = {}, []
    for k, (name, mode, C) in enumerate(spec.tensors):
        chans = []
        for c in range(C):
            nd = Node("in", (), "r", {"role": "x", "k": k, "c": c, "mode": mode, "C": C}, grad=True)
            loads.append(nd)
            chans.append(nd)
        inp[name] = Vec3(chans) if C == 3 else chans[0]
    for j, name in enumerate(spec.floats):
        inp[name] = Node("P", (), "p", j)
    for name in ("x", "y", *SCALAR_PARAMS):
        inp.setdefault(name, None)
    return inp, loads


def build(spec: KernelSpec, kind: str) -> KernelGraph:
    """The graph of one kernel of a kernel family.

    ``kind``: ``"fwd"``, ``"bwd"`` (reverse transform) or ``"jvp"`` (forward transform,
    ``spec.ntan`` tangents).
    """
    g = Graph()
    stores: list[tuple[tuple[Any, ...], Node | float]] = []
    written: tuple[int, ...] = ()
    with g:
        ops = TraceOps(spec.hi_double)
        inp, loads = _inputs(spec)
        fn = formula.FAMILIES[spec.family]
        outs = list(fn(ops, inp, spec.active, spec.need_tint, spec.frame).c)
        if kind == "fwd":
            stores = [(("out", c), o) for c, o in enumerate(outs)]
        elif kind == "bwd":
            seeds = [Node("in", (), "r", {"role": "go", "c": c}) for c in range(3)]
            adj = reverse(g, outs, seeds)
            written_k: list[int] = []
            for k, (name, mode, C) in enumerate(spec.tensors):
                if k not in spec.grad_mask or not any(nd.attr["k"] == k and nd.id in adj for nd in loads):
                    continue  # no path to the output: None in autograd, as in eager
                written_k.append(k)
                for c in range(C):
                    terms = [adj[nd.id] for nd in loads
                             if nd.attr["k"] == k and nd.attr["c"] == c and nd.id in adj]
                    val = terms[0] if terms else 0.0
                    for t in terms[1:]:
                        val = val + t
                    stores.append((("grad", k, c), val))
            written = tuple(written_k)
        elif kind == "jvp":
            T = len(spec.tangent_inputs)
            for j in range(spec.ntan):
                tseeds: dict[int, Node] = {}
                for i, k in enumerate(spec.tangent_inputs):
                    mode, C = spec.tangent_modes[j * T + i], spec.tensors[k][2]
                    if mode == "zero":  # no tangent on this input in direction j: pruned
                        continue
                    for nd in loads:
                        if nd.attr["k"] == k:
                            attr = {"role": "t", "j": j, "i": i, "k": k, "c": nd.attr["c"], "mode": mode,
                                    "C": C}
                            tseeds[nd.id] = Node("in", (), "r", attr)
                for c, tn in enumerate(tangents(g, outs, tseeds)):
                    stores.append((("tout", j, c), tn if tn is not None else 0.0))
        else:
            raise ValueError(f"kind: expected 'fwd', 'bwd' or 'jvp', got {kind!r}")
    return KernelGraph(kind, g, stores, written)
