"""nncg.limits: no tensor, arena or weights blob may need int offsets beyond INT32_MAX."""

from __future__ import annotations

import pytest
from onnx import TensorProto, helper

from nncg.backends import get_target
from nncg.errors import NncgError
from nncg.frontend import import_onnx
from nncg.ir.loops import ArenaPlan, Buffer, Program
from nncg.limits import INT32_MAX, check_program_limits, check_tensor_size, tensor_size_problem
from nncg.passes import PassManager, default_pipeline


def planned_program(proto) -> Program:
    ssse3 = get_target("ssse3")
    return PassManager(default_pipeline(ssse3, "none"), ssse3).run(import_onnx(proto))


def branches_model(side: int):
    """x -> Relu, Sigmoid, Tanh, Elu -> Sum: four activations of side x side floats live at once."""
    ops = ["Relu", "Sigmoid", "Tanh", "Elu"]
    nodes = [helper.make_node(op, ["x"], [f"b{i}"]) for i, op in enumerate(ops)]
    nodes.append(helper.make_node("Sum", [f"b{i}" for i in range(len(ops))], ["y"]))
    graph = helper.make_graph(
        nodes,
        "branches",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 1, side, side])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])


def test_tensor_size_boundaries():
    largest_float_tensor = INT32_MAX // 4
    assert tensor_size_problem((largest_float_tensor,)) is None
    assert "536,870,911 elements of 4 bytes" in tensor_size_problem((largest_float_tensor + 1,))
    assert tensor_size_problem((INT32_MAX,), itemsize=1) is None
    assert tensor_size_problem((INT32_MAX + 1,), itemsize=1) is not None
    with pytest.raises(NncgError, match=r"input 'x' of shape \[1, 3, 100000, 100000\] has 30,000,000,000 elements"):
        check_tensor_size("input 'x'", (1, 3, 100000, 100000))


def test_arena_beyond_int_offsets_is_refused():
    """Every tensor fits (144M floats each), but the four live at once need a 2.1 GiB arena."""
    program = planned_program(branches_model(12000))
    assert program.arena.floats * 4 > INT32_MAX
    with pytest.raises(NncgError, match="activation arena of 2.1 GiB.*--input-shape"):
        check_program_limits(program)


def test_weights_blob_beyond_int_offsets_is_refused():
    program = Program("m", (), (), arena=ArenaPlan(0, 0, 16, weights_floats=2**29))
    with pytest.raises(NncgError, match="weights blob of 2.0 GiB"):
        check_program_limits(program)


def test_buffer_offsets_beyond_int_are_refused():
    """A buffer placed past INT32_MAX bytes (a plan without the arena size, as a custom pass may make)."""
    past = Buffer("w", 2**28, "constant", (2**28,), offset=2**28)
    with pytest.raises(NncgError, match="buffer w .* ends at byte 2.0 GiB"):
        check_program_limits(Program("m", (past,), ()))


def test_programs_within_the_limits_pass():
    program = planned_program(branches_model(1000))
    check_program_limits(program)
    assert 0 < program.arena.floats * 4 <= INT32_MAX
