"""ONNX front end (ONNX -> graph IR), step 3: ConvTranspose, and the weight checks it shares with
Conv. Weights and biases may be constants or computed at runtime (graph inputs included); only
their shapes are needed here.
"""

from __future__ import annotations

from nncg.frontend.context import Context, OnnxOp
from nncg.frontend.windows import conv_transpose_geometry, window_steps
from nncg.ir.graph import ConvTransposeAttrs, Node, Shape
from nncg.safe_text import shown


def weight_kernel(op: OnnxOp, w_shape: Shape) -> Shape:
    """The kernel's spatial extent, from the weight [.., .., k...]; kernel_shape must agree."""
    kernel = tuple(int(k) for k in w_shape[2:])
    declared = op.attr("kernel_shape")
    if declared is not None and tuple(declared) != kernel:
        raise op.error(f"has kernel_shape {list(declared)} but its weight has kernel {list(kernel)}; fix the model")
    return kernel


def check_groups(op: OnnxOp, group: int, c_in: int, c_out: int, w_shape: Shape, w_fits: bool) -> None:
    """Both channel counts split evenly into the groups, and w_fits: the weight agrees with c_in."""
    if group < 1 or c_in % group or c_out % group or not w_fits:
        raise op.error(
            f"has group={group} with {c_in} input channels and weight {list(w_shape)}; "
            "channels must split evenly into the groups"
        )


def bias_input(op: OnnxOp, ctx: Context, c_out: int) -> list[str]:
    """[b] when the optional bias is given (one value per output channel), else []."""
    bias = op.input(2)
    if not bias:
        return []
    if ctx.shape(bias) != (c_out,):
        raise op.error(f"has bias {shown(bias)} of shape {list(ctx.shape(bias))}; expected [{c_out}]")
    return [bias]


def convert_conv_transpose(op: OnnxOp, ctx: Context) -> Node:
    x, w = op.input(0), op.input(1)
    x_shape, w_shape = ctx.shape(x), ctx.shape(w)  # w: [C_in, C_out/group, k...]
    group = int(op.attr("group", 1))
    c_out = w_shape[1] * group
    check_groups(op, group, x_shape[1], c_out, w_shape, w_shape[0] == x_shape[1])
    kernel = weight_kernel(op, w_shape)
    strides, dilations = window_steps(op, len(kernel))
    begin, end, out_spatial = conv_transpose_geometry(op, x_shape[2:], kernel, strides, dilations)
    ctx.set_shape(op, op.node.output[0], (x_shape[0], c_out, *out_spatial))
    attrs = ConvTransposeAttrs(kernel, strides, dilations, begin, end, group)
    return op.ir_node("ConvTranspose", [x, w, *bias_input(op, ctx, c_out)], attrs)
