"""The per-lane graphs of one kernel family, with symbolic loads and stores (any emitter).

:func:`build` traces :func:`torchbrdf.brdf.formula.principled` for a kernel family
(:class:`torchbrdf.kernels.fused._KernelSpec`) and applies the derivative transform the kernel
needs (:func:`.trace.reverse` for the backward, :func:`.trace.tangents` for the JVP). Loads and
stores are left symbolic, so a printer (Triton today; the C printer builds the same graphs with
C load strings) decides how a lane reads and writes memory:

* input loads: ``in`` nodes with ``attr = {"role": "x", "k": input index, "c": channel,
  "mode": "full" | "b1" | "b0", "C": channels}``;
* output-gradient loads (backward): ``{"role": "go", "c": channel}``;
* tangent loads (JVP): ``{"role": "t", "j": tangent, "i": slot, "k", "c", "mode", "C"}``;
* stores: ``(target, node-or-0.0)`` with ``target`` = ``("out", c)``, ``("grad", k, c, C)``
  or ``("tan", j, c)``.

Nothing here knows a derivative rule or a target language.
"""

from __future__ import annotations

from torchbrdf.brdf import formula
from torchbrdf.brdf.principled import SCALAR_PARAMS
from torchbrdf.kernels.trace import Graph, Node, TraceOps, Vec3, reverse, tangents

__all__ = ["build"]


def _inputs(spec):
    """Formula inputs and the load nodes of the tensor inputs of ``spec``."""
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
    inp.setdefault("x", None)
    inp.setdefault("y", None)
    for name in SCALAR_PARAMS:
        inp.setdefault(name, None)
    return inp, loads


def build(spec, kind: str):
    """Graph and stores of one kernel (``kind`` = ``"fwd"``, ``"bwd"`` or ``"jvp"``).

    Returns:
        ``(graph, stores, written)``: ``stores`` a list of ``(target, value)`` (see the module
        docstring); ``written`` the inputs whose gradient the backward writes (those with a
        path to the output and in ``spec.grad_mask``; empty for the other kinds).
    """
    g = Graph()
    written = []
    with g:
        ops = TraceOps(spec.hi_double)
        inp, loads = _inputs(spec)
        outs = list(formula.principled(ops, inp, spec.active, spec.need_tint, spec.frame).c)
        stores = []
        if kind == "fwd":
            stores = [(("out", c), o) for c, o in enumerate(outs)]
        elif kind == "bwd":
            seeds = [Node("in", (), "r", {"role": "go", "c": c}) for c in range(3)]
            adj = reverse(g, outs, seeds)
            for k, (_name, _mode, C) in enumerate(spec.tensors):
                if k not in spec.grad_mask or not any(nd.attr["k"] == k and nd.id in adj for nd in loads):
                    continue  # no path to the output: None in autograd, as in eager
                written.append(k)
                for c in range(C):
                    terms = [adj[nd.id] for nd in loads
                             if nd.attr["k"] == k and nd.attr["c"] == c and nd.id in adj]
                    val = terms[0] if terms else 0.0
                    for t in terms[1:]:
                        val = val + t
                    stores.append((("grad", k, c, C), val))
        elif kind == "jvp":
            T = len(spec.tangent_inputs)
            for j in range(spec.ntan):
                seeds = {}
                slot_modes = spec.tangent_modes[j * T:(j + 1) * T]
                for i, (k, mode) in enumerate(zip(spec.tangent_inputs, slot_modes)):
                    C = spec.tensors[k][2]
                    for nd in loads:
                        if nd.attr["k"] == k:
                            seeds[nd.id] = Node("in", (), "r", {"role": "t", "j": j, "i": i, "k": k,
                                                                "c": nd.attr["c"], "mode": mode, "C": C})
                for c, tn in enumerate(tangents(g, outs, seeds)):
                    stores.append((("tan", j, c), tn if tn is not None else 0.0))
        else:
            raise ValueError(f"kind: expected 'fwd', 'bwd' or 'jvp', got {kind!r}")
    return g, stores, tuple(written)
