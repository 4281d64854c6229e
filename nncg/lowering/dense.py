"""Dense lowering (Gemm, MatMul): y[rows, n] = act(alpha * sum_k x[rows, k] * w[k, n] + beta * b),
n innermost. A constant w is packed [K, N] so n is contiguous and vectorises, or, where the
cache-block pass chose panels, [panel][K][column in panel] so each panel is one contiguous stream; a
runtime w (also transposed or batched) is read where it lives."""

from __future__ import annotations

import numpy as np

from ..ir.graph import DenseAttrs, Node
from ..ir.loops import Affine, Assign, Binary, Const, Expr, Let, Load, LocalRef, Loop, Stmt, Store
from .activation import apply_activation
from .context import LoweringContext, TensorRef, nest, row_major
from .weights import by_panels, permuted, weight_operand


def lower_dense(ctx: LoweringContext, node: Node) -> None:
    attrs: DenseAttrs = node.attrs
    if attrs.panel:
        return _lower_packed(ctx, node)
    x = ctx.ref(node.inputs[0])
    w_rank = len(ctx.graph.shape(node.inputs[1]))
    swap = (*range(w_rank - 2), w_rank - 1, w_rank - 2)  # [..., N, K] read as [..., K, N]
    w = weight_operand(ctx, node.inputs[1], f"w_{node.name}", lambda r: permuted(r, swap) if attrs.trans_w else r)
    k_extent, n_extent = w.shape[-2:]
    bias = weight_operand(ctx, node.inputs[2], f"b_{node.name}") if len(node.inputs) > 2 else None
    out_shape = ctx.graph.shape(node.outputs[0])
    out = ctx.output(node.outputs[0], row_major(len(out_shape)))
    # One loop per leading dim rather than one flattened row loop: x may be in any layout.
    row_loops = [(f"r{i}", d) for i, d in enumerate(out_shape[:-1])]

    def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
        rows = [env[v] for v, _ in row_loops]
        n = env["n"]
        k = Affine.of("k") if k_extent > 1 else Affine()
        x_index = x.at([k, *rows]) if attrs.trans_x else x.at([*_broadcast(x.shape[:-1], rows), k])
        w_index = w.at([*_broadcast(w.shape[:-2], rows[:-1]), k, n])
        product = Binary("*", Load(x.buffer, x_index), Load(w.buffer, w_index))
        update: tuple[Stmt, ...] = (Assign("acc", Binary("+", LocalRef("acc"), product)),)
        reduce = (Loop("k", k_extent, update),) if k_extent > 1 else update
        init, value = _scaled(attrs, _bias_term(attrs, bias, [*rows, n]))
        store = Store(out.buffer, out.at([*rows, n]), apply_activation(value, attrs.activation))
        return (Let("acc", init, (*reduce, store)),)

    ctx.emit(node.name, "Dense", nest([*row_loops, ("n", n_extent)], body, parallel=True))


def _lower_packed(ctx: LoweringContext, node: Node) -> None:
    """w packed in panels of `attrs.panel` columns, [panel][k][column], so each panel's columns are
    one contiguous stream (the cache-block pass chose it): for each panel, the rows x its columns. A
    GEMV reads its panel's reduction as `attrs.streams` segments side by side, each into an
    accumulator of its own, summed before the store."""
    attrs: DenseAttrs = node.attrs
    w = ctx.graph.constants[node.inputs[1]]
    w = w.T if attrs.trans_w else w  # [K, N]
    k_extent, n_extent = w.shape
    x = ctx.ref(node.inputs[0])
    bias = weight_operand(ctx, node.inputs[2], f"b_{node.name}") if len(node.inputs) > 2 else None
    out_shape = ctx.graph.shape(node.outputs[0])
    out = ctx.output(node.outputs[0], row_major(len(out_shape)))
    row_loops = [(f"r{i}", d) for i, d in enumerate(out_shape[:-1])]
    streams = attrs.streams
    segment, tail = divmod(k_extent, streams)
    partials = ["acc", *(f"acc_seg{s}" for s in range(1, streams))]

    def panel_nest(packed: TensorRef, panel: Affine, first_column: Affine, width: int) -> tuple[Stmt, ...]:
        def body(env: dict[str, Affine]) -> tuple[Stmt, ...]:
            rows, c = [env[v] for v, _ in row_loops], env["c"]

            def add(name: str, k: Affine) -> Assign:
                x_load = Load(x.buffer, x.at([*_broadcast(x.shape[:-1], rows), k]))
                product = Binary("*", x_load, Load(packed.buffer, packed.at([panel, k, c])))
                return Assign(name, Binary("+", LocalRef(name), product))

            k = Affine.of("k") if segment > 1 else Affine()
            reduce = _loop("k", segment, tuple(add(name, k + s * segment) for s, name in enumerate(partials)))
            kt = Affine.of("kt") if tail > 1 else Affine()
            reduce += _loop("kt", tail, (add("acc", kt + streams * segment),))
            if streams > 1:
                reduce += (Assign("acc", _pairwise_sum([LocalRef(name) for name in partials])),)
            index = [*rows, first_column + c]
            init, value = _scaled(attrs, _bias_term(attrs, bias, index))
            store = Store(out.buffer, out.at(index), apply_activation(value, attrs.activation))
            stmts: tuple[Stmt, ...] = (*reduce, store)
            for name in reversed(partials[1:]):
                stmts = (Let(name, Const.splat(0.0), stmts),)
            return (Let("acc", init, stmts),)

        return nest([*row_loops, ("c", width)], body, parallel=True)

    def pack(start: int, stop: int, panels: int) -> np.ndarray:
        return _panels(w[:, start:stop], panels)

    ctx.emit(node.name, "Dense", by_panels(ctx, f"w_{node.name}", n_extent, attrs.panel, pack, panel_nest))


def _loop(var: str, extent: int, body: tuple[Stmt, ...]) -> tuple[Stmt, ...]:
    """`body` over var in [0, extent): a loop, the body itself for one step, nothing for none."""
    return (Loop(var, extent, body),) if extent > 1 else body if extent else ()


def _pairwise_sum(terms: list[Expr]) -> Expr:
    """The terms added in pairs (a shorter chain of dependent adds than left to right)."""
    while len(terms) > 1:
        terms = [Binary("+", *terms[i : i + 2]) if i + 1 < len(terms) else terms[i] for i in range(0, len(terms), 2)]
    return terms[0]


def _panels(w: np.ndarray, panels: int) -> np.ndarray:
    """[K, N] -> [panel][k][column in panel]."""
    k_extent, n_extent = w.shape
    return w.reshape(k_extent, panels, n_extent // panels).transpose(1, 0, 2)


def _broadcast(dims: tuple[int, ...], index: list[Affine]) -> list[Affine]:
    """An output index into a tensor whose dims are `dims`, NumPy-broadcast: aligned right, size-1
    dims pinned to 0."""
    index = index[len(index) - len(dims) :]
    return [i if d != 1 else Affine() for i, d in zip(index, dims)]


def _bias_term(attrs: DenseAttrs, bias: TensorRef | None, index: list[Affine]) -> Expr | None:
    if bias is None:
        return None
    term: Expr = Load(bias.buffer, bias.at(_broadcast(bias.shape, index)))
    return term if attrs.beta == 1.0 else Binary("*", term, Const.splat(attrs.beta))


def _scaled(attrs: DenseAttrs, bias: Expr | None) -> tuple[Expr, Expr]:
    """The accumulator's start and the stored value: the bias starts the sum unless alpha scales the
    sum alone, then it is added at the store."""
    if attrs.alpha == 1.0:
        return (bias or Const.splat(0.0)), LocalRef("acc")
    value = Binary("*", LocalRef("acc"), Const.splat(attrs.alpha))
    return Const.splat(0.0), (Binary("+", value, bias) if bias else value)
