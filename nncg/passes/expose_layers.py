"""The debug build of `verify --per-layer`: every float32 graph value the program stores
(Program.values), and ArgMax's int32 indices, becomes an extra output of the generated function,
after the model's own, copied out as a dense row-major array right after the kernel that completes
it. Right then, because later kernels may overwrite its memory (the arena lends it to other
buffers; elementwise kernels compute in place).
Not a pipeline pass: it runs on the planned program, and the normal build never sees it."""

from __future__ import annotations

import math
from dataclasses import replace

from ..ir.c_names import Namespace, buffer_name, layer_name
from ..ir.kinds import BufferRole, DType, Layout
from ..ir.loops import Buffer, Kernel, Program, Stmt, StoredValue
from ..lowering.context import TensorRef, row_major
from ..lowering.reshape import copy_nest


def with_exposed_layers(program: Program) -> Program:
    """The program with one output per stored value (named after it: Buffer.onnx_name is the value)."""
    taken = {b.name.lower() for b in program.buffers}
    layers = {k.name.lower() for k in program.kernels}
    buffer_names = Namespace(lambda name: buffer_name(name, program.name), lambda ident: ident.lower() in taken)
    kernel_names = Namespace(layer_name, lambda ident: ident.lower() in layers)
    outputs, copies = [], {}
    for value in program.values:
        dtype = program.buffer(value.buffer).dtype
        if dtype not in (DType.FLOAT32, DType.INT32):
            continue  # an int8 model's integer values are checked by its float outputs
        out = Buffer(
            buffer_names.claim(f"layer_{value.value}"), math.prod(value.shape), BufferRole.OUTPUT, value.shape,
            Layout.ROW_MAJOR, value.value, dtype=dtype,
        )  # fmt: skip
        kernel = Kernel(kernel_names.claim(f"expose_{value.value}"), "Copy", _copy_out(value, out))
        copies.setdefault(value.layer, []).append(kernel)
        outputs.append(out)
    kernels = tuple(k for kernel in program.kernels for k in (kernel, *copies.get(kernel.name, ())))
    return replace(program, buffers=program.buffers + tuple(outputs), kernels=kernels)


def _copy_out(value: StoredValue, out: Buffer) -> tuple[Stmt, ...]:
    """The value's elements, wherever its layout, halo or Concat slab puts them, into `out` row-major."""
    src = TensorRef(value.buffer, value.shape, value.order, value.halo)
    return copy_nest(src, TensorRef(out.name, value.shape, row_major(len(value.shape))))
