"""Tracing the shared formula into a per-lane expression graph, and differentiating the graph.

The IR
------
A :class:`Graph` is a list of :class:`Node` s in creation (= topological) order. A node is
one per-lane scalar value: ``op``, ``args`` (nodes or Python floats), ``kind`` and ``attr``.

Kinds: ``'r'`` a value in the compute dtype (float or double), ``'d'`` a float64 value (the
half-vector terms of float32 inputs), ``'p'`` a runtime Python float (double, the same for
every lane), ``'b'`` a boolean mask. Python numbers stay Python numbers and fold in double,
exactly as the eager code folds them.

Ops: ``in`` (attr: ``{"k": input index, "c": channel, "role": "x"|"t"|"go", ...}``), ``P``
(runtime float ``attr``), ``const`` (attr: the value), ``add sub mul div neg recip sqrt rsqrt
log log1p exp2 abs``, ``maxc`` (clamp_min of a tensor), ``max2`` (``torch.maximum`` of two
values), ``pmax`` (max of runtime floats), ``clamp`` (x, lo, hi), ``where`` (mask, a, b),
``gt lt ge le eq and`` (masks), ``tod``/``tor`` (convert to double / to the compute type).

Vectors are :class:`Vec3` (three nodes) with broadcasting arithmetic, so the formula's
``base * w`` means the same per channel as on ``(*, 3)`` tensors.

Derivatives are graph transforms that add nodes to the same graph: :func:`reverse` (adjoints,
for the backward kernel) and :func:`tangents` (forward mode, for the JVP kernel). Their rules
are ATen's autograd formulas (``clamp`` passes the gradient where the input lies within the
bounds, ``where`` routes it to the selected branch, ...). An emitter (C today, Triton next)
only prints nodes.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable
from typing import Any, TypeAlias, TypeGuard, overload

__all__ = ["Graph", "Node", "Vec3", "TraceOps", "reverse", "tangents", "live_order"]

# A per-lane value the formula handles while tracing: a node, a 3-vector of nodes, or a Python
# number (folded in double, as the eager code folds it).
Operand: TypeAlias = "Node | Vec3 | float"


class Graph:
    """The nodes of one traced kernel; use as a context manager while building."""

    current: "Graph | None" = None

    def __init__(self) -> None:
        self.nodes: list[Node] = []

    def __enter__(self) -> Graph:
        self._prev, Graph.current = Graph.current, self
        return self

    def __exit__(self, *exc: object) -> None:
        Graph.current = self._prev


class Node:
    """One per-lane scalar value of the graph (see the module docstring); appended to ``Graph.current``."""

    __slots__ = ("id", "op", "args", "kind", "attr", "grad")

    def __init__(self, op: str, args: Iterable[Node | float], kind: str, attr: Any = None,
                 grad: bool | None = None) -> None:
        self.op, self.kind, self.attr = op, kind, attr
        self.args: tuple[Node | float, ...] = tuple(args)
        # Does this value depend on a differentiable input? ('in' nodes say so themselves.)
        self.grad: bool = grad if grad is not None else any(isinstance(a, Node) and a.grad for a in self.args)
        g = Graph.current
        if g is None:
            raise RuntimeError("a trace Node must be created inside a `with Graph():` block")
        self.id = len(g.nodes)
        g.nodes.append(self)

    def __repr__(self) -> str:
        return f"Node({self.id}, {self.op}, {self.kind})"

    # arithmetic -------------------------------------------------------------------------
    def __add__(self, o: Node | float) -> Node:
        return _bin("add", self, o)

    def __radd__(self, o: Node | float) -> Node:
        return _bin("add", o, self)

    def __sub__(self, o: Node | float) -> Node:
        return _bin("sub", self, o)

    def __rsub__(self, o: Node | float) -> Node:
        return _bin("sub", o, self)

    def __mul__(self, o: Node | float) -> Node:
        return _bin("mul", self, o)

    def __rmul__(self, o: Node | float) -> Node:
        return _bin("mul", o, self)

    def __truediv__(self, o: Node | float) -> Node:
        return _div(self, o)

    def __rtruediv__(self, o: Node | float) -> Node:
        return _div(o, self)

    def __neg__(self) -> Node:
        return Node("neg", (self,), self.kind)

    def __gt__(self, o: Node | float) -> Node:
        return _cmp("gt", self, o)

    def __lt__(self, o: Node | float) -> Node:
        return _cmp("lt", self, o)

    def __ge__(self, o: Node | float) -> Node:
        return _cmp("ge", self, o)

    def __le__(self, o: Node | float) -> Node:
        return _cmp("le", self, o)

    def eq(self, o: Node | float) -> Node:
        """The mask ``self == o`` (a method: ``__eq__`` stays identity, nodes are dict keys)."""
        return _cmp("eq", self, o)

    def __and__(self, o: Node) -> Node:
        return Node("and", (self, o), "b")


class Vec3:
    """Three channel nodes (a ``(*, 3)`` value); arithmetic broadcasts scalars over channels."""

    __slots__ = ("c",)

    def __init__(self, chans: Iterable[Node | float]) -> None:
        self.c: tuple[Node | float, ...] = tuple(chans)

    def _map(self, o, fn):
        oc = o.c if isinstance(o, Vec3) else (o, o, o)
        return Vec3(fn(a, b) for a, b in zip(self.c, oc))

    def __add__(self, o: Operand) -> Vec3:
        return self._map(o, lambda a, b: a + b)

    def __radd__(self, o: Operand) -> Vec3:
        return self._map(o, lambda a, b: b + a)

    def __sub__(self, o: Operand) -> Vec3:
        return self._map(o, lambda a, b: a - b)

    def __rsub__(self, o: Operand) -> Vec3:
        return self._map(o, lambda a, b: b - a)

    def __mul__(self, o: Operand) -> Vec3:
        return self._map(o, lambda a, b: a * b)

    def __rmul__(self, o: Operand) -> Vec3:
        return self._map(o, lambda a, b: b * a)

    def __truediv__(self, o: Operand) -> Vec3:
        return self._map(o, lambda a, b: a / b)

    def __rtruediv__(self, o: Operand) -> Vec3:
        return self._map(o, lambda a, b: b / a)


def _is_tensor(a: object) -> TypeGuard[Node]:
    return isinstance(a, Node) and a.kind in ("r", "d")


def _kind(a) -> str:
    return a.kind if isinstance(a, Node) else "c"


def const(value: float, kind: str) -> Node:
    """A constant node of kind ``kind`` holding ``float(value)``."""
    return Node("const", (), kind, float(value))


def _to_kind(a, kind):
    if not isinstance(a, Node):
        return const(a, kind)
    if a.kind == kind or (a.kind == "p" and kind == "d"):
        return a
    if a.kind == "p" and kind == "r":
        return Node("tor", (a,), "r")
    raise TypeError(f"implicit mix of {a.kind} and {kind}")


def _target(*xs) -> str:
    ks = {_kind(x) for x in xs}
    for k in ("r", "d", "p"):
        if k in ks:
            return k
    return "c"


def _bin(op, a, b):
    if isinstance(b, Vec3):
        return Vec3(_bin(op, a, c) for c in b.c)
    t = _target(a, b)
    if t == "c":
        return {"add": a + b, "sub": a - b, "mul": a * b}[op]
    return Node(op, (_to_kind(a, t), _to_kind(b, t)), t)


def _div(a, b):
    if isinstance(b, Vec3):
        return Vec3(_div(a, c) for c in b.c)
    if _target(a, b) == "c":
        return a / b
    if _is_tensor(b) and not _is_tensor(a):
        # torch: ``number / tensor`` is ``tensor.reciprocal() * number``.
        return _bin("mul", Node("recip", (b,), b.kind), a)
    return _bin("div", a, b)


def _cmp(op, a, b):
    t = _target(a, b)
    return Node(op, (_to_kind(a, t), _to_kind(b, t)), "b")


def _un(op, a):
    if isinstance(a, Vec3):
        return Vec3(_un(op, c) for c in a.c)
    return Node(op, (a,), a.kind)


class TraceOps:
    """The ``ops`` namespace of :mod:`torchbrdf.brdf.formula` on graph nodes.

    ``hi_double``: the compute type is float and ``to_hi`` converts to double (float32
    inputs); otherwise ``to_hi``/``to_compute`` are the identity.
    """

    def __init__(self, hi_double: bool) -> None:
        self.hi_double = hi_double

    @staticmethod
    def sqrt(a: Operand) -> Operand:
        """Square root (``math.sqrt`` on Python numbers)."""
        return math.sqrt(a) if isinstance(a, numbers.Real) else _un("sqrt", a)

    @staticmethod
    def rsqrt(a: Node | Vec3) -> Node | Vec3:
        """``1 / sqrt(x)``."""
        return _un("rsqrt", a)

    @staticmethod
    def log(a: Node | Vec3) -> Node | Vec3:
        """Natural log."""
        return _un("log", a)

    @staticmethod
    def log1p(a: Node | Vec3) -> Node | Vec3:
        """``log(1 + x)``."""
        return _un("log1p", a)

    @staticmethod
    def exp2(a: Node | Vec3) -> Node | Vec3:
        """``2^x``."""
        return _un("exp2", a)

    @staticmethod
    def abs(a: Node | Vec3) -> Node | Vec3:
        """``|x|``."""
        return _un("abs", a)

    @staticmethod
    def maximum(a: Node, b: Node | float) -> Node:
        """``torch.maximum(a, b)`` of two per-lane values."""
        t = _target(a, b)
        return Node("max2", (_to_kind(a, t), _to_kind(b, t)), t)

    @overload
    @staticmethod
    def clamp(a: Vec3, lo: float, hi: float) -> Vec3: ...
    @overload
    @staticmethod
    def clamp(a: Node, lo: float, hi: float) -> Node: ...
    @staticmethod
    def clamp(a: Node | Vec3, lo: float, hi: float) -> Node | Vec3:
        """``x`` clamped to ``[lo, hi]``."""
        if isinstance(a, Vec3):
            # The channels of a traced vector that reaches clamp are nodes.
            return Vec3(TraceOps.clamp(c, lo, hi) for c in a.c)  # type: ignore[arg-type]
        return Node("clamp", (a, _to_kind(lo, a.kind), _to_kind(hi, a.kind)), a.kind)

    @overload
    @staticmethod
    def clamp_min(a: Vec3, lo: float) -> Vec3: ...
    @overload
    @staticmethod
    def clamp_min(a: Node, lo: float) -> Node: ...
    @overload
    @staticmethod
    def clamp_min(a: float, lo: float) -> float: ...
    @staticmethod
    def clamp_min(a: Operand, lo: float) -> Operand:
        """``max(x, lo)`` (``torch.clamp(x, min=lo)`` on tensors)."""
        if isinstance(a, Vec3):
            return Vec3(TraceOps.clamp_min(c, lo) for c in a.c)
        if _is_tensor(a):
            return Node("maxc", (a, _to_kind(lo, a.kind)), a.kind)
        if isinstance(a, Node):  # runtime Python float: max(a, lo)
            return Node("pmax", (a, _to_kind(lo, "p")), "p")
        return max(a, lo)

    @overload
    @staticmethod
    def where(c: Node, a: Node | float, b: Node | float) -> Node: ...
    @overload
    @staticmethod
    def where(c: Node, a: Operand, b: Operand) -> Node | Vec3: ...
    @staticmethod
    def where(c: Node, a: Operand, b: Operand) -> Node | Vec3:
        """``a`` where ``c``, else ``b``."""
        if isinstance(a, Vec3) or isinstance(b, Vec3):
            ac = a.c if isinstance(a, Vec3) else (a, a, a)
            bc = b.c if isinstance(b, Vec3) else (b, b, b)
            return Vec3(TraceOps.where(c, x, y) for x, y in zip(ac, bc))
        t = _target(a, b)
        t = "r" if t in ("c", "p") else t
        return Node("where", (c, _to_kind(a, t), _to_kind(b, t)), t)

    @staticmethod
    def dot(a: Vec3, b: Vec3) -> Node | float:
        """Dot product over the channels, ``(*, 3) -> (*, 1)``."""
        ac, bc = a.c, b.c
        return (ac[0] * bc[0] + ac[1] * bc[1]) + ac[2] * bc[2]

    @staticmethod
    def cross_norm2(a: Vec3, b: Vec3) -> Node | float:
        """``|a × b|²``, ``(*, 1)``."""
        ac, bc = a.c, b.c
        c0 = ac[1] * bc[2] - ac[2] * bc[1]
        c1 = ac[2] * bc[0] - ac[0] * bc[2]
        c2 = ac[0] * bc[1] - ac[1] * bc[0]
        return (c0 * c0 + c1 * c1) + c2 * c2

    @staticmethod
    def channel(x: Vec3, i: int) -> Node | float:
        """Channel ``i`` of a colour, ``(*, 1)``."""
        return x.c[i]

    @staticmethod
    def as_tensor(a: Node | float) -> Node:
        """A number as a compute-dtype value."""
        return a if _is_tensor(a) else _to_kind(a, "r")

    def as_color(self, a: Operand) -> Vec3:
        """A colour ``(*, 3)``; a number becomes grey."""
        if isinstance(a, Vec3):
            return a
        b = self.as_tensor(a)
        return Vec3((b, b, b))

    @overload
    def to_hi(self, a: Vec3) -> Vec3: ...
    @overload
    def to_hi(self, a: Node | float) -> Node | float: ...
    def to_hi(self, a: Operand) -> Operand:
        """To float64 when computing in float32."""
        if not self.hi_double:
            return a
        if isinstance(a, Vec3):
            return Vec3(self.to_hi(c) for c in a.c)
        return Node("tod", (a,), "d")

    @overload
    def to_compute(self, a: Vec3) -> Vec3: ...
    @overload
    def to_compute(self, a: Node | float) -> Node | float: ...
    def to_compute(self, a: Operand) -> Operand:
        """Back to the compute dtype."""
        if not self.hi_double:
            return a
        if isinstance(a, Vec3):
            return Vec3(self.to_compute(c) for c in a.c)
        return Node("tor", (a,), "r")

    def mask(self, valid: Node, f: Operand | None) -> Node | Vec3:
        """``f`` where ``valid``, exactly 0 elsewhere, ``(*, 3)``."""
        if f is None:
            f = 0.0
        return self.where(valid, f if isinstance(f, Vec3) else Vec3((f, f, f)), 0.0)


def live_order(graph: Graph, roots: Iterable[Node | float | None]) -> list[Node]:
    """The nodes ``roots`` depend on, in graph order."""
    live = set()
    stack = [r for r in roots if isinstance(r, Node)]
    while stack:
        nd = stack.pop()
        if nd.id in live:
            continue
        live.add(nd.id)
        stack.extend(a for a in nd.args if isinstance(a, Node))
    return [nd for nd in graph.nodes if nd.id in live]


# ---------------------------------------------------------------------------------------------
# Derivatives as graph transforms
# ---------------------------------------------------------------------------------------------

def _zero(kind):
    return const(0.0, kind)


def _sel(c, a, b):
    return Node("where", (c, a, b), a.kind)


def _adjoint(nd: Node, g: Node) -> list:
    """Contributions ``(arg index, node)`` of the adjoint ``g`` of ``nd`` to its arguments."""
    # Nodes or Python floats; each op's rule knows which of its arguments are nodes.
    a: tuple[Any, ...] = nd.args
    op = nd.op
    k = nd.kind
    if op == "add":
        return [(0, g), (1, g)]
    if op == "sub":
        return [(0, g), (1, -g)]
    if op == "mul":
        return [(0, g * a[1]), (1, g * a[0])]
    if op == "div":
        return [(0, g / a[1]), (1, -g * ((a[0] / a[1]) / a[1]))]
    if op == "neg":
        return [(0, -g)]
    if op == "recip":
        return [(0, -g * (nd * nd))]
    if op == "sqrt":
        return [(0, g / (const(2.0, k) * nd))]
    if op == "rsqrt":
        return [(0, const(-0.5, k) * g * (nd * nd * nd))]
    if op == "log":
        return [(0, g / a[0])]
    if op == "log1p":
        return [(0, g / (a[0] + const(1.0, k)))]
    if op == "exp2":  # ATen: grad * result * ln 2
        return [(0, g * nd * const(math.log(2.0), k))]
    if op == "max2":  # ATen: a tie gives each argument half the gradient
        half = _sel(a[0].eq(a[1]), g / const(2.0, k), g)
        return [(0, _sel(a[0] < a[1], _zero(k), half)), (1, _sel(a[0] > a[1], _zero(k), half))]
    if op == "abs":
        return [(0, _sel(a[0] < _zero(k), -g, _sel(a[0] > _zero(k), g, _zero(k))))]
    if op == "maxc":
        return [(0, _sel(a[0] >= a[1], g, _zero(k)))]
    if op == "clamp":
        return [(0, _sel((a[0] >= a[1]) & (a[0] <= a[2]), g, _zero(k)))]
    if op == "where":
        return [(1, _sel(a[0], g, _zero(k))), (2, _sel(a[0], _zero(k), g))]
    if op == "tod":
        return [(0, Node("tor", (g,), "r"))]
    if op == "tor":
        return [(0, Node("tod", (g,), "d"))]
    return []


def reverse(graph: Graph, outs: list[Any], seeds: list[Any],
            stop: frozenset[int] | set[int] = frozenset()) -> dict[int, Any]:
    """Reverse mode: adjoint nodes of every differentiable node ``outs`` depend on.

    Args:
        graph: the graph holding ``outs``; the adjoint nodes are added to it.
        outs: output nodes.
        seeds: their adjoints (nodes, same length).
        stop: ids of nodes that receive their adjoint but do not pass it on (the boundary of a
            loop body: the adjoint is accumulated there and propagated further after the loop).

    Returns:
        ``{node id: adjoint node}`` (only for nodes that receive a gradient).
    """
    order = live_order(graph, outs)
    contrib: dict[int, list] = {}
    for o, s in zip(outs, seeds):
        if isinstance(o, Node) and o.grad:
            contrib.setdefault(o.id, []).append(s)
    adj = {}
    for nd in reversed(order):
        if not nd.grad or nd.id not in contrib:
            continue
        terms = contrib[nd.id]
        g = terms[0]
        for t in terms[1:]:
            g = g + t
        adj[nd.id] = g
        if nd.op == "in" or nd.id in stop:
            continue
        for idx, e in _adjoint(nd, g):
            arg = nd.args[idx]
            if isinstance(arg, Node) and arg.grad:
                contrib.setdefault(arg.id, []).append(e)
    return adj


def _add_opt(a, b):
    return b if a is None else (a if b is None else a + b)


def _tangent(nd: Node, t: list):
    """The tangent of ``nd`` from its arguments' tangents ``t`` (``None`` = zero)."""
    # Nodes or Python floats; each op's rule knows which of its arguments are nodes.
    a: tuple[Any, ...] = nd.args
    op = nd.op
    k = nd.kind
    if op == "add":
        return _add_opt(t[0], t[1])
    if op == "sub":
        return t[0] if t[1] is None else (-t[1] if t[0] is None else t[0] - t[1])
    if op == "mul":
        return _add_opt(None if t[0] is None else t[0] * a[1], None if t[1] is None else a[0] * t[1])
    if op == "div":
        return _add_opt(None if t[0] is None else t[0] / a[1],
                        None if t[1] is None else -t[1] * ((a[0] / a[1]) / a[1]))
    if op == "neg":
        return -t[0]
    if op == "recip":
        return -t[0] * (nd * nd)
    if op == "sqrt":
        return t[0] / (const(2.0, k) * nd)
    if op == "rsqrt":
        return const(-0.5, k) * t[0] * (nd * nd * nd)
    if op == "log":
        return t[0] / a[0]
    if op == "log1p":
        return t[0] / (a[0] + const(1.0, k))
    if op == "exp2":
        return t[0] * nd * const(math.log(2.0), k)
    if op == "max2":  # ATen: t_b + w (t_a - t_b), w = 1, 0 or 1/2 at a tie
        ta = t[0] if t[0] is not None else _zero(k)
        tb = t[1] if t[1] is not None else _zero(k)
        w = _sel(a[0].eq(a[1]), const(0.5, k), _sel(a[0] > a[1], const(1.0, k), _zero(k)))
        return tb + w * (ta - tb)
    if op == "abs":
        return _sel(a[0] < _zero(k), -t[0], _sel(a[0] > _zero(k), t[0], _zero(k)))
    if op == "maxc":
        return _sel(a[0] >= a[1], t[0], _zero(k))
    if op == "clamp":
        return _sel((a[0] >= a[1]) & (a[0] <= a[2]), t[0], _zero(k))
    if op == "where":
        if t[1] is None and t[2] is None:
            return None
        return _sel(a[0], t[1] if t[1] is not None else _zero(k), t[2] if t[2] is not None else _zero(k))
    if op == "tod":
        return Node("tod", (t[0],), "d")
    if op == "tor":
        return Node("tor", (t[0],), "r")
    return None


def tangents(graph: Graph, outs: list[Any], seeds: dict[int, Any]) -> list[Any]:
    """Forward mode: tangent nodes of ``outs`` given ``seeds`` = ``{input node id: tangent node}``.

    Returns one tangent node per output (``None`` where the output does not depend on a seed).
    """
    order = live_order(graph, outs)
    tan: dict[int, Node] = dict(seeds)
    for nd in order:
        if nd.op == "in" or not nd.grad:
            continue
        ts = [tan.get(x.id) if isinstance(x, Node) else None for x in nd.args]
        if all(x is None for x in ts):
            continue
        r = _tangent(nd, ts)
        if r is not None:
            tan[nd.id] = r
    return [tan.get(o.id) if isinstance(o, Node) else None for o in outs]
