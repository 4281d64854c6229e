"""The dtypes of graph values: what each op reads and writes. Float ops read and write float32 only,
so an int8 value can reach float arithmetic only through an explicit DequantizeLinear."""

from __future__ import annotations

from collections.abc import Callable

from .graph import Graph, Node
from .kinds import DType

FLOAT32, INT8, UINT8, INT16, INT32 = DType.FLOAT32, DType.INT8, DType.UINT8, DType.INT16, DType.INT32
ACTIVATIONS = (INT8, UINT8)  # the types of quantized activations
# What the generated function takes and writes: float32 or quantized values, and as outputs also
# int32 (ArgMax's indices, a ConvInteger's or MatMulInteger's sums).
INPUT_DTYPES = (FLOAT32, *ACTIVATIONS)
OUTPUT_DTYPES = (*INPUT_DTYPES, INT32)
# Ops that move elements without computing on them: their output has their input's dtype.
TYPE_PRESERVING = ("MaxPool", "Reshape", "Identity", "Transpose", "Concat", "Pad")
# Ops whose output holds indices: int32 (ONNX's are int64; C89 has no guaranteed 64-bit type).
INDEX_OPS = ("ArgMax", "ArgMin")
# The quantized ops, with the dtypes each input slot may have.
QUANTIZED_INPUTS: dict[str, tuple[tuple[DType, ...], ...]] = {
    "QuantizeLinear": ((FLOAT32,),),
    "DequantizeLinear": (ACTIVATIONS,),
    "QLinearConv": (ACTIVATIONS, (INT8, INT16), (INT32,), (FLOAT32,)),
    "QLinearDense": (ACTIVATIONS, (INT8, INT16), (INT32,), (FLOAT32,)),
    "QLinearAdd": (ACTIVATIONS, ACTIVATIONS),
    "QLinearGlobalAveragePool": (ACTIVATIONS,),
    "QLinearAveragePool": (ACTIVATIONS,),
    "QLinearSoftmax": (ACTIVATIONS, (FLOAT32,)),
    "QLinearLookup": (ACTIVATIONS, ACTIVATIONS),
    "QLinearMul": (ACTIVATIONS, ACTIVATIONS),
    "ConvInteger": (ACTIVATIONS, (INT8, INT16), (INT32,), (FLOAT32,), (FLOAT32,)),
    "MatMulInteger": (ACTIVATIONS, (INT8, INT16), (INT32,), (FLOAT32,), (FLOAT32,)),
}
# Quantized ops that write float32 (their int32 result dequantised in the store).
DEQUANTIZING_OPS = ("DequantizeLinear", "ConvInteger", "MatMulInteger")
# Of those, the ones that write their int32 result as it is where it is not `dequantized`.
INTEGER_PRODUCTS = ("ConvInteger", "MatMulInteger")


def moves_integers(node: Node) -> bool:
    """Whether the node only moves its input's elements, so it takes integers as they are: the
    TYPE_PRESERVING ops, and a nearest-neighbour Resize that extrapolates nothing."""
    if node.op == "Resize":
        attrs = node.attrs
        return attrs.mode == "nearest" and attrs.coordinate_transformation_mode != "tf_crop_and_resize"
    return node.op in TYPE_PRESERVING


def output_dtype(node: Node, dtype_of: Callable[[str], DType]) -> DType:
    """The dtype of the node's outputs (every op here has one output type), given its inputs'."""
    if moves_integers(node):
        return dtype_of(node.inputs[0])
    if node.op in INDEX_OPS:
        return INT32
    if node.op in ("QuantizeLinear", "QLinearLookup"):
        return node.attrs.dtype
    if node.op in INTEGER_PRODUCTS and not node.attrs.dequantized:
        return INT32
    if node.op in QUANTIZED_INPUTS and node.op not in DEQUANTIZING_OPS:
        return node.attrs.out.dtype
    return FLOAT32


def float_ops_reading_integers(graph: Graph) -> list[tuple[Node, str]]:
    """(node, input) for every float op that reads an integer value."""
    return [
        (node, name)
        for node in graph.nodes
        if not moves_integers(node) and node.op not in QUANTIZED_INPUTS
        for name in node.inputs
        if graph.dtype(name) != FLOAT32
    ]


def graph_dtype_problems(graph: Graph) -> list[str]:
    """Every node reads the dtypes its op takes and its outputs have the dtype it writes."""
    problems = []
    for node in graph.nodes:
        dtypes = [graph.dtype(name) for name in node.inputs]
        if moves_integers(node):
            allowed = [(dtypes[0],)] * len(dtypes) if dtypes else []
        elif node.op in QUANTIZED_INPUTS:
            allowed = list(QUANTIZED_INPUTS[node.op])
            if node.op == "DequantizeLinear":
                allowed = [(node.attrs.dtype,)]
        else:
            allowed = [(FLOAT32,)] * len(dtypes)
        for name, dtype, ok in zip(node.inputs, dtypes, allowed, strict=False):
            if dtype not in ok:
                problems.append(f"node {node.name} ({node.op}) reads {name} of type {dtype}, not {'/'.join(ok)}")
        expected = output_dtype(node, graph.dtype)
        problems += [
            f"node {node.name} ({node.op}) writes {out} of type {graph.dtype(out)}, not {expected}"
            for out in node.outputs
            if graph.dtype(out) != expected
        ]
    problems += [
        f"graph input {v.name} is {graph.dtype(v.name)}, not {'/'.join(INPUT_DTYPES)}"
        for v in graph.inputs
        if graph.dtype(v.name) not in INPUT_DTYPES
    ]
    problems += [
        f"graph output {v.name} is {graph.dtype(v.name)}, not {'/'.join(OUTPUT_DTYPES)}"
        for v in graph.outputs
        if graph.dtype(v.name) not in OUTPUT_DTYPES
    ]
    return problems
