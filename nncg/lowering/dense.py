"""Dense lowering (Gemm, MatMul): y[rows, n] = act(b[n] + sum_k x[rows, k] * w[k, n]), n innermost."""

from __future__ import annotations

from ..ir.graph import DenseAttrs, Node
from ..ir.loops import Affine, Assign, Binary, Const, Let, Load, LocalRef, Loop, Stmt, Store
from .activation import apply_activation
from .context import LoweringContext, nest, row_major


def lower_dense(ctx: LoweringContext, node: Node) -> None:
    attrs: DenseAttrs = node.attrs
    x = ctx.ref(node.inputs[0])
    w = ctx.add_constant(f"w_{node.name}", ctx.graph.constants[node.inputs[1]])  # [K, N]
    k_extent, n_extent = w.shape
    bias = None
    if len(node.inputs) > 2:
        bias = ctx.add_constant(f"b_{node.name}", ctx.graph.constants[node.inputs[2]])
    out_shape = ctx.graph.shape(node.outputs[0])
    out = ctx.output(node.outputs[0], row_major(len(out_shape)))
    # One loop per leading dim rather than one flattened row loop: x may be in any layout.
    row_loops = [(f"r{i}", d) for i, d in enumerate(out_shape[:-1])]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        rows = [env[v] for v, _ in row_loops]
        n = env["n"]
        k = Affine.of("k") if k_extent > 1 else Affine()
        x_index = x.at([k, *rows]) if attrs.trans_x else x.at([*rows, k])
        product = Binary("*", Load(x.buffer, x_index), Load(w.buffer, w.at([k, n])))
        update: tuple[Stmt, ...] = (Assign("acc", Binary("+", LocalRef("acc"), product)),)
        reduce = (Loop("k", k_extent, update),) if k_extent > 1 else update
        init = Load(bias.buffer, bias.at([n])) if bias else Const.splat(0.0)
        store = Store(out.buffer, out.at([*rows, n]), apply_activation(LocalRef("acc"), attrs.activation))
        return (Let("acc", init, (*reduce, store)),)

    ctx.emit(node.name, "Dense", nest([*row_loops, ("n", n_extent)], body, parallel=True))
