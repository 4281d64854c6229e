"""ONNX front end, step 2b: QDQ models (what onnxruntime.quantization.quantize_static writes) become
QOperator models, as onnxruntime's own QDQ transformer rewrites them, so that one converter per
QOperator op serves both formats.

A float op whose inputs come from DequantizeLinear nodes and whose only reader is a QuantizeLinear
computes in integers: Conv becomes QLinearConv, MatMul QLinearMatMul, and in onnxruntime's
com.microsoft domain Gemm QGemm, Add QLinearAdd, Mul QLinearMul, Concat QLinearConcat,
GlobalAveragePool QLinearGlobalAveragePool, AveragePool QLinearAveragePool, Softmax QLinearSoftmax,
LeakyRelu QLinearLeakyRelu and Sigmoid QLinearSigmoid; HardSwish and Tanh become NNCG's own
QLinearHardSwish and QLinearTanh (these four are table lookups, see ops_qlookup.py). A ConvInteger or MatMulInteger
whose result a Cast to float32 reads, then maybe a Mul by a constant and an Add of one, becomes one
node (ops_integer.py).
A Relu or a Clip between the op and its QuantizeLinear is folded into the output range: quantising
is monotonic, so clamping before it is clamping its result; the real bounds travel beside the nodes
(QdqNotes), never as ONNX attributes a model could also carry. MaxPool, Reshape, Flatten,
Transpose, Pad and nearest Resize between a DequantizeLinear and a QuantizeLinear of the same scale
and zero point move the integers as they are (Pad's constant value quantised). Weights and biases
are the constants that folding dequantized (Folded.dequantized keeps the DequantizeLinear they came
from). Every QuantizeLinear and DequantizeLinear left over stays: an explicit quantise or
dequantise kernel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import onnx
from onnx import helper

from nncg.frontend.folding import Folded, NamedNode, live_nodes
from nncg.ir.names import fresh_name

CONTRIB = "com.microsoft"
NNCG_DOMAIN = "nncg"  # the domain of NNCG's own QOperator nodes (a model cannot import it)
PASS_THROUGH = ("MaxPool", "Reshape", "Flatten", "Transpose")
ACTIVATION_TYPES = (np.int8, np.uint8)


@dataclass
class QdqNotes:
    """What the rewritten nodes need beyond their ONNX inputs and attributes, by the node's output:
    the real range of the Relu and Clip nodes folded into it, and which int8 pools onnxruntime
    computes in uint8 (see QAveragePoolAttrs)."""

    output_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    uint8_pools: set[str] = field(default_factory=set)


class _Model:
    """The live nodes with their producers and readers, and the names the rewrite adds."""

    def __init__(self, folded: Folded, outputs: list[str], notes: QdqNotes):
        self.folded = folded
        self.notes = notes
        self.outputs = set(outputs)
        self.nodes = list(folded.nodes)
        self.producer = {o: (node, name) for node, name in self.nodes for o in node.output}
        self.readers: dict[str, list[onnx.NodeProto]] = {}
        for node, _ in self.nodes:
            for i in node.input:
                self.readers.setdefault(i, []).append(node)

    def const(self, name: str) -> np.ndarray | None:
        return self.folded.constants.get(name) if name else None

    def sole_reader(self, value: str, op_type: str) -> onnx.NodeProto | None:
        readers = self.readers.get(value, [])
        if value in self.outputs or len(readers) != 1 or readers[0].op_type != op_type:
            return None
        return readers[0]

    def live_dq(self, value: str) -> onnx.NodeProto | None:
        """The per-tensor DequantizeLinear of an 8-bit activation that computes `value`."""
        found = self.producer.get(value)
        node = found[0] if found else None
        if node is None or node.op_type != "DequantizeLinear" or not _per_tensor(self, node):
            return None
        return node


def _per_tensor(model: _Model, node: onnx.NodeProto) -> bool:
    """A (De)QuantizeLinear with a constant scalar scale and an 8-bit scalar zero point."""
    scale, zero = model.const(node.input[1]), model.const(node.input[2]) if len(node.input) > 2 else None
    if scale is None or scale.size != 1 or (len(node.input) > 2 and node.input[2] and zero is None):
        return False
    return zero is None or (zero.size == 1 and zero.dtype in ACTIVATION_TYPES)


def _quantize_params(node: onnx.NodeProto) -> list[str]:
    """scale and zero point inputs ("" where the zero point is omitted)."""
    return [node.input[1], node.input[2] if len(node.input) > 2 else ""]


def _output_q(model: _Model, value: str) -> tuple[onnx.NodeProto, list[onnx.NodeProto]] | None:
    """The QuantizeLinear that reads `value`, alone, possibly through Relu or Clip nodes (returned
    too, to fold into the output range)."""
    clamps = []
    while True:
        readers = model.readers.get(value, [])
        if value in model.outputs or len(readers) != 1:
            return None
        node = readers[0]
        if node.op_type == "QuantizeLinear" and _per_tensor(model, node) and node.input[0] == value:
            return node, clamps
        if node.op_type == "Relu" or (node.op_type == "Clip" and _constant_clip(model, node)):
            clamps.append(node)
            value = node.output[0]
            continue
        return None


def _constant_clip(model: _Model, node: onnx.NodeProto) -> bool:
    if any(a.name in ("min", "max") for a in node.attribute):
        return True  # opset < 11: the bounds are attributes
    return all(model.const(i) is not None for i in node.input[1:] if i)


def _dequantized(model: _Model, value: str, dtypes: tuple) -> onnx.NodeProto | None:
    """The DequantizeLinear a constant weight or bias was folded from, of one of `dtypes`."""
    node = model.folded.dequantized.get(value)
    if node is None or model.const(node.input[0]) is None or model.const(node.input[0]).dtype not in dtypes:
        return None
    return node


def fuse_qdq(folded: Folded, outputs: list[str]) -> tuple[list[NamedNode], QdqNotes]:
    """The live nodes with every QDQ group that computes in integers replaced by its QOperator node,
    and the notes on those nodes."""
    changed = True
    nodes = folded.nodes
    notes = QdqNotes()
    while changed:
        model = _Model(replace(folded, nodes=nodes), outputs, notes)
        changed = False
        for node, name in model.nodes:
            rewrite = REWRITES.get(node.op_type)
            replacement = rewrite(model, node) if rewrite else None
            if replacement is None:
                continue
            new, removed = replacement
            kept = [(n, nm) for n, nm in model.nodes if all(n is not r for r in removed)]
            nodes = [(new, name) if n is node else (n, nm) for n, nm in kept]
            nodes = live_nodes(nodes, outputs)
            changed = True
            break
    return nodes, notes


def _q_output(model: _Model, op: onnx.NodeProto) -> tuple[onnx.NodeProto, list] | None:
    return _output_q(model, op.output[0])


def _fused(model: _Model, node: onnx.NodeProto, q: onnx.NodeProto, clamps: list[onnx.NodeProto]):
    """The rewrite's result: `node` replacing q and the clamps, whose real range is noted."""
    low, high = -np.inf, np.inf
    for clamp in clamps:
        lo, hi = _clip_bounds(model, clamp)
        low, high = max(low, lo), min(high, hi)
    if clamps:
        model.notes.output_ranges[node.output[0]] = (float(low), float(high))
    return node, [q, *clamps]


def _clip_bounds(model: _Model, node: onnx.NodeProto) -> tuple[float, float]:
    if node.op_type == "Relu":
        return 0.0, np.inf
    attrs = {a.name: a.f for a in node.attribute}
    if attrs:
        return attrs.get("min", -np.inf), attrs.get("max", np.inf)
    bounds = [model.const(i) if i else None for i in (*node.input[1:], "", "")[:2]]
    return tuple(float(b) if b is not None else default for b, default in zip(bounds, (-np.inf, np.inf)))


def _node(op_type: str, inputs: list[str], output: str, source: onnx.NodeProto, domain: str = ""):
    """The QOperator node with the float op's attributes (but Gemm's transA and beta, which QGemm
    lacks: only transA=0 and beta=1 are rewritten)."""
    node = helper.make_node(op_type, inputs, [output], domain=domain)
    node.attribute.extend([a for a in source.attribute if a.name not in ("transA", "beta")])
    return node


def _conv(model: _Model, conv: onnx.NodeProto):
    dq_x = model.live_dq(conv.input[0])
    w = _dequantized(model, conv.input[1], (np.int8, np.uint8))
    b = _dequantized(model, conv.input[2], (np.int32,)) if len(conv.input) > 2 and conv.input[2] else None
    out = _q_output(model, conv)
    if dq_x is None or w is None or out is None or (len(conv.input) > 2 and conv.input[2] and b is None):
        return None
    q, clamps = out
    inputs = [dq_x.input[0], *_quantize_params(dq_x), *w.input[:3], *_quantize_params(q)] + ([b.input[0]] if b else [])
    return _fused(model, _node("QLinearConv", inputs, q.output[0], conv), q, clamps)


def _gemm(model: _Model, gemm: onnx.NodeProto):
    attrs = {a.name: helper.get_attribute_value(a) for a in gemm.attribute}
    if attrs.get("transA", 0) or attrs.get("alpha", 1.0) != 1.0 or attrs.get("beta", 1.0) != 1.0:
        return None
    dq_x = model.live_dq(gemm.input[0])
    w = _dequantized(model, gemm.input[1], (np.int8, np.uint8))
    has_bias = len(gemm.input) > 2 and gemm.input[2]
    b = _dequantized(model, gemm.input[2], (np.int32,)) if has_bias else None
    out = _q_output(model, gemm)
    if dq_x is None or w is None or out is None or (has_bias and b is None):
        return None
    if has_bias and model.const(b.input[0]).ndim != 1:
        return None
    q, clamps = out
    inputs = [dq_x.input[0], *_quantize_params(dq_x), *w.input[:3], b.input[0] if b else "", *_quantize_params(q)]
    return _fused(model, _node("QGemm", inputs, q.output[0], gemm, CONTRIB), q, clamps)


def _matmul(model: _Model, matmul: onnx.NodeProto):
    dq_x = model.live_dq(matmul.input[0])
    w = _dequantized(model, matmul.input[1], (np.int8, np.uint8))
    out = _q_output(model, matmul)
    if dq_x is None or w is None or out is None:
        return None
    q, clamps = out
    inputs = [dq_x.input[0], *_quantize_params(dq_x), *w.input[:3], *_quantize_params(q)]
    return _fused(model, _node("QLinearMatMul", inputs, q.output[0], matmul), q, clamps)


def _binary(model: _Model, node: onnx.NodeProto, qlinear_op: str):
    """An Add or Mul of two DequantizeLinear outputs (or one and a constant folded from one), broadcast."""
    operands = [model.live_dq(i) or _dequantized_per_tensor(model, i) for i in node.input]
    out = _q_output(model, node)
    if None in operands or out is None:
        return None
    q, clamps = out
    a, b = operands
    inputs = [a.input[0], *_quantize_params(a), b.input[0], *_quantize_params(b), *_quantize_params(q)]
    return _fused(model, _node(qlinear_op, inputs, q.output[0], node, CONTRIB), q, clamps)


def _add(model: _Model, add: onnx.NodeProto):
    return _binary(model, add, "QLinearAdd")


def _mul(model: _Model, mul: onnx.NodeProto):
    return _binary(model, mul, "QLinearMul")


def _concat(model: _Model, concat: onnx.NodeProto):
    """A Concat of DequantizeLinear outputs (or constants folded from them) of one 8-bit type."""
    parts = [model.live_dq(i) or _dequantized_per_tensor(model, i) for i in concat.input]
    q = model.sole_reader(concat.output[0], "QuantizeLinear")
    if None in parts or q is None or not _per_tensor(model, q):
        return None
    if len({_zero_point_type(model, node) for node in (*parts, q)}) != 1:
        return None
    inputs = [*_quantize_params(q)] + [name for dq in parts for name in (dq.input[0], *_quantize_params(dq))]
    return _node("QLinearConcat", inputs, q.output[0], concat, CONTRIB), [q]


def _integer_product(model: _Model, node: onnx.NodeProto):
    """A ConvInteger or MatMulInteger whose int32 result only a Cast to float32 reads, and that
    possibly only a Mul by a constant (and that, possibly, only an Add of a constant): the op in
    NNCG's domain with two more inputs (the Mul's constant or "" for none, the Add's or ""), which
    computes the float32 result in its kernel's store, so that no int32 tensor is written."""
    cast = model.sole_reader(node.output[0], "Cast")
    to = next((a.i for a in cast.attribute if a.name == "to"), None) if cast is not None else None
    if to != onnx.TensorProto.FLOAT:
        return None
    inputs = [*node.input, *[""] * (4 - len(node.input))]
    mul = model.sole_reader(cast.output[0], "Mul")
    scale = _other_constant(model, mul, cast.output[0]) if mul is not None else None
    if scale is None:
        return _node(node.op_type, [*inputs, "", ""], cast.output[0], node, NNCG_DOMAIN), [cast]
    last, removed, bias = mul, [cast, mul], ""
    add = model.sole_reader(mul.output[0], "Add")
    if add is not None and _other_constant(model, add, mul.output[0]) is not None:
        last, removed, bias = add, [cast, mul, add], _other_constant(model, add, mul.output[0])
    return _node(node.op_type, [*inputs, scale, bias], last.output[0], node, NNCG_DOMAIN), removed


def _other_constant(model: _Model, node: onnx.NodeProto, value: str) -> str | None:
    """The input of a two-input `node` other than `value`, if it is a float32 constant."""
    others = [i for i in node.input if i != value]
    if len(node.input) != 2 or len(others) != 1:
        return None
    constant = model.const(others[0])
    return others[0] if constant is not None and constant.dtype == np.float32 else None


def _zero_point_type(model: _Model, node: onnx.NodeProto):
    zero = model.const(_quantize_params(node)[1])
    return np.dtype(np.uint8) if zero is None else zero.dtype


def _dequantized_per_tensor(model: _Model, value: str) -> onnx.NodeProto | None:
    """The per-tensor DequantizeLinear an 8-bit constant operand was folded from."""
    node = _dequantized(model, value, ACTIVATION_TYPES)
    return node if node is not None and _per_tensor(model, node) else None


def _pool(qop: str) -> Callable:
    """GlobalAveragePool or AveragePool between a DequantizeLinear and a QuantizeLinear as `qop`;
    an int8 one noted in uint8_pools: onnxruntime computes it in uint8 (see QAveragePoolAttrs)."""

    def rewrite(model: _Model, pool: onnx.NodeProto):
        dq_x = model.live_dq(pool.input[0])
        out = _q_output(model, pool)
        if dq_x is None or out is None or out[1]:
            return None
        q = out[0]
        inputs = [dq_x.input[0], *_quantize_params(dq_x), *_quantize_params(q)]
        zero = model.const(_quantize_params(q)[1])
        if zero is not None and zero.dtype == np.int8:
            model.notes.uint8_pools.add(q.output[0])
        return _node(qop, inputs, q.output[0], pool, CONTRIB), [q]

    return rewrite


def _softmax(model: _Model, softmax: onnx.NodeProto):
    """A Softmax between a DequantizeLinear and a QuantizeLinear as QLinearSoftmax (without its
    opset attribute: the converter takes the model's)."""
    dq_x = model.live_dq(softmax.input[0])
    q = model.sole_reader(softmax.output[0], "QuantizeLinear")
    if dq_x is None or q is None or not _per_tensor(model, q):
        return None
    inputs = [dq_x.input[0], *_quantize_params(dq_x), *_quantize_params(q)]
    return _node("QLinearSoftmax", inputs, q.output[0], softmax, CONTRIB), [q]


def _lookup(qop: str, domain: str = CONTRIB) -> Callable:
    """A unary op between a DequantizeLinear and a QuantizeLinear as `qop`, a table lookup."""

    def rewrite(model: _Model, op: onnx.NodeProto):
        dq_x = model.live_dq(op.input[0])
        q = model.sole_reader(op.output[0], "QuantizeLinear")
        if dq_x is None or q is None or not _per_tensor(model, q):
            return None
        inputs = [dq_x.input[0], *_quantize_params(dq_x), *_quantize_params(q)]
        return _node(qop, inputs, q.output[0], op, domain), [q]

    return rewrite


def _pass_through(model: _Model, op: onnx.NodeProto):
    """MaxPool, Reshape, Flatten or Transpose of the integers, when the scale and zero point do not change."""
    dq_x = model.live_dq(op.input[0])
    q = model.sole_reader(op.output[0], "QuantizeLinear")
    if dq_x is None or q is None or not _per_tensor(model, q) or not _same_quantization(model, dq_x, q):
        return None
    node = helper.make_node(op.op_type, [dq_x.input[0], *op.input[1:]], [q.output[0]])
    node.attribute.extend(op.attribute)
    return node, [q]


def _resize(model: _Model, resize: onnx.NodeProto):
    """A nearest-neighbour Resize of the integers (it picks elements), when the scale and zero point
    do not change; tf_crop_and_resize, which can write an extrapolation value, stays float."""
    attrs = {a.name: helper.get_attribute_value(a) for a in resize.attribute}
    if (
        attrs.get("mode", b"nearest") != b"nearest"
        or attrs.get("coordinate_transformation_mode") == b"tf_crop_and_resize"
    ):
        return None
    return _pass_through(model, resize)


def _pad(model: _Model, pad: onnx.NodeProto):
    """A Pad (opset 11 on: pads and value are inputs) of the integers, when the scale and zero point
    do not change; the constant value becomes the integer QuantizeLinear gives it (0: the zero point)."""
    value = model.const(pad.input[2]) if len(pad.input) > 2 and pad.input[2] else np.zeros((), np.float32)
    found = _pass_through(model, pad)
    if found is None or len(pad.input) < 2 or value is None or value.size != 1:
        return None
    node, removed = found
    scale, zero = (model.const(i) for i in _quantize_params(removed[0]))
    dtype = np.dtype(np.uint8) if zero is None else zero.dtype
    integer = _quantized(float(value.reshape(())), float(scale.reshape(())), 0 if zero is None else int(zero), dtype)
    name = fresh_name(f"{node.output[0]}_pad_value", model.folded.constants, model.folded.shapes, model.producer)
    model.folded.constants[name] = np.array(integer, dtype)
    del node.input[2:]
    node.input.extend([name, *pad.input[3:]])
    return node, removed


def _quantized(value: float, scale: float, zero: int, dtype: np.dtype) -> int:
    """QuantizeLinear of one value: divided in float32, rounded half to even, saturated."""
    info = np.iinfo(dtype)
    with np.errstate(over="ignore"):
        q = np.rint(np.float32(value) / np.float32(scale))
    return int(np.clip(q + zero, info.min, info.max)) if np.isfinite(q) else (info.min if q < 0 else info.max)


def _same_quantization(model: _Model, a: onnx.NodeProto, b: onnx.NodeProto) -> bool:
    def params(node):
        scale, zero = (model.const(i) for i in _quantize_params(node))
        zero = np.zeros((), np.uint8) if zero is None else zero
        return float(scale.reshape(())), int(zero.reshape(())), zero.dtype

    return params(a) == params(b)


REWRITES: dict[str, Callable] = {
    "Conv": _conv,
    "Gemm": _gemm,
    "MatMul": _matmul,
    "Add": _add,
    "Mul": _mul,
    "Concat": _concat,
    "GlobalAveragePool": _pool("QLinearGlobalAveragePool"),
    "AveragePool": _pool("QLinearAveragePool"),
    "Softmax": _softmax,
    "LeakyRelu": _lookup("QLinearLeakyRelu"),
    "Sigmoid": _lookup("QLinearSigmoid"),
    "HardSwish": _lookup("QLinearHardSwish", NNCG_DOMAIN),
    "Tanh": _lookup("QLinearTanh", NNCG_DOMAIN),
    **dict.fromkeys(PASS_THROUGH, _pass_through),
    "Pad": _pad,
    "Resize": _resize,
    "ConvInteger": _integer_product,
    "MatMulInteger": _integer_product,
}
