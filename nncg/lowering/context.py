"""Lowering state: buffers, layouts and C-safe names shared by the per-op lowerings."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from ..errors import NncgError
from ..ir.c_names import Namespace, buffer_name, layer_name
from ..ir.graph import Graph
from ..ir.kinds import DType, Layout
from ..ir.loops import Affine, Buffer, Kernel, Loop, Stmt
from .halo import conv_halos, zero_halo
from .slabs import concat_slices


def row_major(rank: int) -> tuple[int, ...]:
    return tuple(range(rank))


def channels_last(rank: int) -> tuple[int, ...]:
    """Physical dim order N, spatial..., C: the output-channel loop becomes contiguous (vectorisable)."""
    return (0, *range(2, rank), 1) if rank >= 3 else row_major(rank)


def layout_of(shape: tuple[int, ...], order: tuple[int, ...]) -> Layout:
    return Layout.ROW_MAJOR if order == row_major(len(shape)) else Layout.CHANNELS_LAST


@dataclass(frozen=True)
class TensorRef:
    """Where a logical tensor lives: a buffer and the physical order of its logical dims. With a
    `halo` ((before, after) per logical dim), the buffer holds the tensor inside a border of zeros
    that padded convolutions read instead of checking bounds. With a `lead`, the tensor (one image,
    channels last) starts that many rows into its buffer, whose first rows an in-place depthwise
    Conv's output takes (in_place.py); they are not zeros."""

    buffer: str
    shape: tuple[int, ...]
    order: tuple[int, ...]  # logical dims from outermost to innermost in memory
    halo: tuple[tuple[int, int], ...] = ()
    lead: int = 0

    @property
    def stored_shape(self) -> tuple[int, ...]:
        """The shape with the halo included."""
        if not self.halo:
            return self.shape
        return tuple(d + before + after for d, (before, after) in zip(self.shape, self.halo))

    @property
    def strides(self) -> tuple[int, ...]:
        shape = self.stored_shape
        strides = [0] * len(shape)
        step = 1
        for dim in reversed(self.order):
            strides[dim] = step
            step *= shape[dim]
        return tuple(strides)

    def at(self, index) -> Affine:
        """Flat offset of a logical index (a sequence of Affine/str/int, one per dim)."""
        offset = Affine.of(self.lead * self.strides[2]) if self.lead else Affine()
        for d, (i, stride) in enumerate(zip(index, self.strides)):
            offset = offset + (Affine.of(i) + (self.halo[d][0] if self.halo else 0)) * stride
        return offset

    @property
    def spatial_ranges(self) -> list[tuple[int, int]]:
        """Per spatial dim (2, 3, ...), the positions that may be read: [-halo before, size + halo after)."""
        halo = self.halo or ((0, 0),) * len(self.shape)
        return [(-halo[d][0], self.shape[d] + halo[d][1]) for d in range(2, len(self.shape))]

    @property
    def is_row_major(self) -> bool:
        physical = [d for d in self.order if self.shape[d] != 1]
        return physical == sorted(physical) and not self.halo


def same_memory_order(a: TensorRef, b: TensorRef) -> bool:
    """Whether both place every element at the same offset (dims of extent 1 do not matter)."""
    if a.halo or b.halo:
        return a == replace(b, buffer=a.buffer)
    return all(sa == sb for sa, sb, d in zip(a.strides, b.strides, a.shape) if d != 1)


def dim_vars(rank: int, prefix: str = "") -> tuple[str, ...]:
    """Readable loop-variable names for the logical dims of a tensor."""
    names = {2: "mn", 3: "ncl", 4: "nchw", 5: "ncdhw"}.get(rank)
    return tuple(prefix + c for c in names) if names else tuple(f"{prefix}i{d}" for d in range(rank))


def nest(
    loops: list[tuple[str, int]], inner: Callable[[dict[str, Affine]], tuple[Stmt, ...]], parallel: bool
) -> tuple[Stmt, ...]:
    """Loops outermost first; an extent-1 loop is not emitted, its variable is 0."""
    env = {var: (Affine.of(var) if extent > 1 else Affine()) for var, extent in loops}
    body = inner(env)
    for var, extent in reversed(loops):
        if extent > 1:
            body = (Loop(var, extent, body, parallel=parallel),)
    return body


def layer_names(graph: Graph) -> tuple[Namespace, dict[str, str]]:
    """The kernels' namespace and each node's layer (kernel) name in it, claimed in graph order."""
    names = Namespace(layer_name)
    return names, {node.name: names.claim(node.name) for node in graph.nodes}


class LoweringContext:
    """Allocates buffers and remembers where each graph value lives. Buffers and layers have C names
    of their own (nncg/ir/c_names.py); a node's kernel keeps the node's name, which --tune and the
    per-layer pass parameters use as the layer's identity."""

    def __init__(self, graph: Graph, program: str, halos: bool | str = "auto", requantize: str = "float"):
        self.graph = graph
        self.program = program
        self.requantize = requantize  # the form of requantisation: float or fixed (lowering/requantize.py)
        self.buffers: list[Buffer] = []
        self.constants: dict[str, np.ndarray] = {}
        self.refs: dict[str, TensorRef] = {}
        self.kernels: list[Kernel] = []
        self._buffer_names = Namespace(lambda name: buffer_name(name, program))
        self._kernel_names, self._layers = layer_names(graph)
        self.pending_copies: list[tuple[str, TensorRef, TensorRef]] = []
        self.halos = conv_halos(graph, blocked_only=halos == "auto") if halos else {}
        self.slabs = concat_slices(graph)  # Concat inputs their producers write in place
        self.written_as_is: set[str] = set()  # graph outputs their producer writes in their own layout
        self.in_place: dict[str, tuple[str, int]] = {}  # depthwise output -> (its input, the input's lead)

    def add_buffer(
        self, name: str, role: str, shape, order, onnx_name: str = "", dtype: DType = DType.FLOAT32
    ) -> TensorRef:
        shape = tuple(int(d) for d in shape)
        ident = self._buffer_names.claim(name)
        size = int(np.prod(shape)) if shape else 1
        self.buffers.append(Buffer(ident, size, role, shape, layout_of(shape, order), onnx_name, dtype=dtype))
        return TensorRef(ident, shape, tuple(order))

    def add_constant(self, name: str, data: np.ndarray) -> TensorRef:
        """A packed weight array; its logical shape is the packed shape, row-major. Integer weights
        (the int8 path) keep their type, any other is float32."""
        integer = data.dtype.kind in "iu"
        data = np.ascontiguousarray(data, dtype=None if integer else np.float32)
        ref = self.add_buffer(name, "constant", data.shape, row_major(data.ndim), dtype=DType(data.dtype.name))
        self.constants[ref.buffer] = data
        return ref

    def ref(self, value: str) -> TensorRef:
        """Where a value (or a graph constant, stored row-major on first use) lives."""
        if value not in self.refs and self.graph.is_constant(value):
            self.refs[value] = self.add_constant("c_" + value, self.graph.constants[value])
        return self.refs[value]

    def output(self, value: str, order: tuple[int, ...]) -> TensorRef:
        """Allocates the buffer a node writes `value` to, in the layout the lowering prefers.

        A graph output is row-major at the function boundary; where the preferred layout differs
        in memory, the node writes an internal buffer and a copy kernel converts it afterwards (unless
        `written_as_is` has it: a banded group's output, where the copy's buffer would be the largest;
        or the output is int32 — ArgMax's indices, ConvInteger's and MatMulInteger's sums — written in
        the output's order as before the arena held int32: whether a copy pays there is unmeasured)."""
        shape, dtype = self.graph.shape(value), self.graph.dtype(value)
        preferred = TensorRef("", shape, tuple(order))
        if self.graph.is_graph_output(value):
            target = self.refs[value]
            if same_memory_order(preferred, target) or value in self.written_as_is or dtype == DType.INT32:
                return target
            temp = self.add_buffer("t_" + value, "internal", shape, order, dtype=dtype)
            self.pending_copies.append((value, temp, target))
            return temp
        if value in self.slabs:
            slab = self._slab(value, order)
            if slab is not None:
                self.refs[value] = slab
                return slab
        if value in self.in_place:  # a depthwise Conv's output over its input (in_place.py)
            ref = replace(self.refs[self.in_place[value][0]], shape=shape, lead=0)
        elif value in self.halos:
            halo = self.halos[value]
            stored = TensorRef("", shape, tuple(order), halo).stored_shape
            ref = replace(self.add_buffer("t_" + value, "internal", stored, order), shape=shape, halo=halo)
            self.emit_helper("halo_" + ref.buffer, "ZeroHalo", zero_halo(ref))
        else:
            ref = self._add_tensor(value, shape, order, dtype)
        self.refs[value] = ref
        return ref

    def _add_tensor(self, value: str, shape, order, dtype) -> TensorRef:
        """The buffer of an internal tensor; the input of an in-place depthwise Conv `lead` rows
        down a buffer that many rows higher."""
        lead = next((lead for x, lead in self.in_place.values() if x == value), 0)
        if not lead:
            return self.add_buffer("t_" + value, "internal", shape, order, dtype=dtype)
        if tuple(order) != (0, 2, 3, 1):
            raise NncgError(f"the input '{value}' of an in-place depthwise Conv is not stored channels last")
        stored = (shape[0], shape[1], shape[2] + lead, shape[3])
        return replace(self.add_buffer("t_" + value, "internal", stored, order, dtype=dtype), shape=shape, lead=lead)

    def _slab(self, value: str, order: tuple[int, ...]) -> TensorRef | None:
        """`value` as a view of its slab of the Concat output (allocated now, in the layout of the
        first producer to ask), or None when that output is laid out in another order."""
        whole, axis, offset = self.slabs[value]
        out = self.refs.get(whole) or self.output(whole, order)
        if out.order != tuple(order):
            return None
        size = self.graph.shape(value)[axis]
        halo = list(out.halo or ((0, 0),) * len(out.shape))
        before, after = halo[axis]
        halo[axis] = (before + offset, after + out.shape[axis] - offset - size)
        shape = tuple(size if d == axis else extent for d, extent in enumerate(out.shape))
        return TensorRef(out.buffer, shape, out.order, tuple(halo))

    def emit(self, node_name: str, op: str, body: tuple[Stmt, ...]) -> None:
        """Adds a kernel of the node `node_name`: the first is named as the node, any further one (a
        resize done one dim at a time) gets a name of its own."""
        layer = self._layers[node_name]
        if any(k.name == layer for k in self.kernels):
            layer = self._kernel_names.claim(layer)
        self.kernels.append(Kernel(layer, op, body))

    def emit_helper(self, name: str, op: str, body: tuple[Stmt, ...]) -> None:
        """Adds a kernel no node has (a copy, a zero halo), named apart from every layer."""
        self.kernels.append(Kernel(self._kernel_names.claim(name), op, body))
