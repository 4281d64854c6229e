"""Loop passes checked on their output IR (Before/Expected), without a C compiler."""

import numpy as np
import pytest
from helpers import target
from test_ops import conv_model

import nncg
from nncg.errors import NncgError
from nncg.ir.loops import (
    Affine,
    Assign,
    Binary,
    Bound,
    Broadcast,
    Buffer,
    Call,
    Const,
    If,
    Kernel,
    Let,
    Load,
    LocalRef,
    Loop,
    Program,
    Store,
    walk_stmts,
)
from nncg.ir.verify import verify_program
from nncg.passes import PassManager, default_pipeline
from nncg.passes.inline_constants import inline_constants
from nncg.passes.unroll import emitted_size, mark_unroll, unroll
from nncg.passes.vectorize import vectorize

A = Affine.of


def program(body, constants=None, size=64):
    constants = constants or {"w": np.arange(16, dtype=np.float32)}
    buffers = (
        Buffer("x", size, "input"),
        Buffer("y", size, "output"),
        *(Buffer(name, arr.size, "constant") for name, arr in constants.items()),
    )
    return Program("f", buffers, (Kernel("k", "Test", tuple(body)),), constants)


def scale_nest(extent_i=2, extent_c=8):
    """y[i*C + c] = x[i*C + c] * w[c]: parallel over i and c."""
    C = extent_c
    store = Store("y", A("i") * C + "c", Binary("*", Load("x", A("i") * C + "c"), Load("w", A("c"))))
    return (Loop("i", extent_i, (Loop("c", C, (store,), parallel=True),), parallel=True),)


# ----------------------------------------------------------------------------------------- unroll


def test_unroll_level_1_keeps_outer_loop_and_expands_inner():
    out = unroll(program(scale_nest(2, 3)), level=1)
    expected = (
        Loop(
            "i",
            2,
            tuple(
                Store("y", A("i") * 3 + c, Binary("*", Load("x", A("i") * 3 + c), Load("w", A(c)))) for c in range(3)
            ),
            parallel=True,
        ),
    )
    assert out.kernels[0].body == expected


def test_unroll_level_0_leaves_no_loop_and_none_leaves_all():
    full = unroll(program(scale_nest(2, 3)), level=0)
    assert not [s for s in walk_stmts(full.kernels[0].body) if isinstance(s, Loop)]
    assert len(full.kernels[0].body) == 6
    assert full.kernels[0].body[5] == Store("y", A(5), Binary("*", Load("x", A(5)), Load("w", A(2))))
    assert unroll(program(scale_nest()), level=None) == program(scale_nest())


def test_unroll_levels_count_loops_through_lets_and_ifs():
    inner = Loop("k", 3, (Assign("acc", LocalRef("acc")),))
    body = (Loop("o", 4, (Let("acc", Const.splat(0.0), (If((Bound(A("o"), 1, None),), (inner,)),)),)),)
    marked = mark_unroll(body, 1)
    assert marked[0].kind == "serial"
    assert marked[0].body[0].body[0].body[0].kind == "unrolled"


def test_unroll_budget_keeps_loops_whose_expansion_is_too_big():
    # o (4) x k (3) stores: the o loop would expand to 12 statements, the k loop to 3
    body = (Loop("o", 4, (Loop("k", 3, (Store("y", A("o") * 3 + A("k"), Load("x", A("k"))),)),)),)
    assert mark_unroll(body, 0, budget=12)[0].kind == "unrolled"
    capped = mark_unroll(body, 0, budget=11)
    assert capped[0].kind == "serial" and capped[0].body[0].kind == "unrolled"
    assert mark_unroll(body, 0, budget=2)[0].body[0].kind == "serial"


def test_unroll_total_budget_shrinks_the_nest_budget_until_the_program_fits():
    # scale_nest(4, 8): unrolling everything gives 32 stores; unrolling c only, 1 loop + 8 stores
    assert emitted_size(unroll(program(scale_nest(4, 8)), level=0).kernels[0].body) == 32
    capped = unroll(program(scale_nest(4, 8)), level=0, total=16)
    assert emitted_size(capped.kernels[0].body) == 9
    assert [s.var for s in walk_stmts(capped.kernels[0].body) if isinstance(s, Loop)] == ["i"]


def test_unrolling_resolves_border_checks_statically():
    # for k in 0..3: if 0 <= k - 1: y[k] = x[k - 1]   -> only k = 1, 2 survive, unguarded
    guarded = If((Bound(A("k") - 1, 0, None),), (Store("y", A("k"), Load("x", A("k") - 1)),))
    out = unroll(program([Loop("k", 3, (guarded,), parallel=True)]), level=0)
    assert out.kernels[0].body == (Store("y", A(1), Load("x", A(0))), Store("y", A(2), Load("x", A(1))))


# -------------------------------------------------------------------------------------- vectorize


def test_vectorize_channels_into_vector_loads_and_broadcasts():
    out = vectorize(program(scale_nest(2, 8)), target(4))
    vec = Store(
        "y",
        A("i") * 8 + A("c") * 4,
        Binary("*", Load("x", A("i") * 8 + A("c") * 4, 4), Load("w", A("c") * 4, 4)),
    )
    expected = (Loop("i", 2, (Loop("c", 2, (vec,), parallel=True, lanes=4),), parallel=True),)
    assert out.kernels[0].body == expected
    assert verify_program(out) == []


def test_vectorize_adds_scalar_tail_and_broadcasts_invariant_operands():
    # y[c] = x[0] * w[c] for c in 0..6: one vector block (loop elided) and a 2-iteration scalar tail
    store = Store("y", A("c"), Binary("*", Load("x", A(0)), Load("w", A("c"))))
    out = vectorize(program([Loop("c", 6, (store,), parallel=True)]), target(4))
    body = out.kernels[0].body
    assert body[0] == Store("y", A(0), Binary("*", Broadcast(Load("x", A(0)), 4), Load("w", A(0), 4)))
    tail = Store("y", A("c") + 4, Binary("*", Load("x", A(0)), Load("w", A("c") + 4)))
    assert body[1] == Loop("c", 2, (tail,), parallel=True)
    assert verify_program(out) == []


def test_vectorize_makes_reduction_locals_vectors():
    update = Assign("acc", Binary("+", LocalRef("acc"), Binary("*", Load("x", A("k")), Load("w", A("k") * 4 + "c"))))
    let = Let("acc", Const.splat(0.0), (Loop("k", 2, (update,)), Store("y", A("c"), LocalRef("acc"))))
    out = vectorize(program([Loop("c", 4, (let,), parallel=True)]), target(4))
    let_v = out.kernels[0].body[0]
    assert let_v.init == Const.splat(0.0, 4)
    assert let_v.body[1] == Store("y", A(0), LocalRef("acc", 4))
    assert let_v.body[0].body[0].value.b.a == Broadcast(Load("x", A("k")), 4)
    assert verify_program(out) == []


def channel_nest(channels):
    """y[i*C + c] = x[i] * w[c] + x[i]: a broadcast, a contiguous load, a store along c."""
    x = Load("x", A("i"))
    store = Store("y", A("i") * channels + "c", Binary("+", Binary("*", x, Load("w", A("c"))), x))
    return (Loop("i", 2, (Loop("c", channels, (store,), parallel=True),), parallel=True),)


def vector_blocks(body):
    """(first channel, lanes, iterations) of each store along c in the i loop; lanes 1: scalar."""
    out = []
    for stmt in body[0].body:
        store = stmt.body[0] if isinstance(stmt, Loop) else stmt
        start = store.index.substitute({"i": 0, "c": 0}).const
        out.append((start, store.value.lanes, stmt.extent if isinstance(stmt, Loop) else 1))
    return out


@pytest.mark.parametrize(
    "channels, blocks",
    [
        (12, [(0, 8, 1), (8, 4, 1)]),  # one 8-lane and one 4-lane block, no scalar loop
        (20, [(0, 16, 1), (16, 4, 1)]),
        (8, [(0, 8, 1)]),
        (44, [(0, 16, 2), (32, 8, 1), (40, 4, 1)]),
        (14, [(0, 8, 1), (8, 4, 1), (12, 1, 2)]),  # 2 channels left: a scalar tail loop
        (3, None),  # narrower than every width: left scalar
    ],
)
def test_vectorize_splits_channels_into_several_widths(channels, blocks):
    p = program(channel_nest(channels), {"w": np.arange(channels, dtype=np.float32)}, size=2 * channels)
    out = vectorize(p, target(16, 8, 4))
    assert verify_program(out) == []
    if blocks is None:
        assert out == p
    else:
        assert vector_blocks(out.kernels[0].body) == blocks


def test_vectorize_widths_print_each_block_with_its_own_width():
    # 12 channels: 8 lanes at c = 0, 4 lanes at c = 8; w is loaded, x broadcast, at each block's width
    out = vectorize(program(channel_nest(12), {"w": np.arange(12, dtype=np.float32)}, size=24), target(16, 8, 4))
    eight, four = out.kernels[0].body[0].body
    x = Load("x", A("i"))
    assert eight == Store(
        "y", A("i") * 12, Binary("+", Binary("*", Broadcast(x, 8), Load("w", A(0), 8)), Broadcast(x, 8))
    )
    assert four == Store(
        "y", A("i") * 12 + 8, Binary("+", Binary("*", Broadcast(x, 4), Load("w", A(8), 4)), Broadcast(x, 4))
    )


def test_vectorize_widths_come_from_the_target():
    assert PassManager("lower,vectorize", target(16, 8, 4)).pipeline == "lower,vectorize,plan-memory"
    with pytest.raises(NncgError, match="no parameter 'lanes'"):
        PassManager("lower,vectorize{lanes=8/4}", target(4))
    assert ",vectorize," in default_pipeline(nncg.get_target("avx512"))
    assert "vectorize" not in default_pipeline(nncg.get_target("ansi-c"))
    assert "lanes=" not in default_pipeline(nncg.get_target("avx512"))


def test_backends_reject_widths_they_cannot_print():
    m = conv_model((1, 3, 6, 7), 12, (3, 3), pads=[1, 1, 1, 1])
    program = PassManager("lower,vectorize", nncg.get_target("avx2")).run(nncg.import_onnx(m))
    with pytest.raises(NncgError, match="ssse3 cannot print 8-lane vectors"):
        nncg.emit(program, "ssse3")


@pytest.mark.parametrize(
    "loop",
    [
        Loop("c", 8, (Store("y", A("c") * 2, Load("x", A("c"))),), parallel=True),  # strided store
        Loop("c", 8, (Store("y", A("c"), Load("x", A("c"))),), parallel=False),  # a reduction axis
        Loop("c", 8, (Store("y", A("c"), Call("exp", Load("x", A("c") * 2))),), parallel=True),  # strided, in a call
        Loop("c", 2, (Store("y", A("c"), Load("x", A("c"))),), parallel=True),  # shorter than a vector
    ],
)
def test_vectorize_leaves_ineligible_loops_scalar(loop):
    p = program([loop])
    assert vectorize(p, target(4)) == p


# ------------------------------------------------------------------------------- inline-constants


def test_inline_constants_writes_literals_and_drops_unused_arrays():
    p = unroll(program(scale_nest(1, 4)), level=0)  # w read at constant indices only
    out = inline_constants(p)
    assert out.kernels[0].body[2] == Store("y", A(2), Binary("*", Load("x", A(2)), Const((2.0,))))
    assert "w" not in out.constants and all(b.role != "constant" for b in out.buffers)


def test_inline_constants_keeps_arrays_read_in_loops_and_inlines_vectors():
    p = vectorize(program(scale_nest(1, 8)), target(4))  # w read as w[4*c:4] inside a loop
    assert inline_constants(p) == p
    vec = unroll(p, level=0)
    out = inline_constants(vec)
    assert out.kernels[0].body[1].value.b == Const((4.0, 5.0, 6.0, 7.0))


def test_unrolling_prunes_border_check_sides_that_always_hold():
    # for o in 0..4: for k in 0..3: if 0 <= o + k - 1 < 4: y[o] = x[o + k - 1]
    pos = A("o") + "k" - 1
    guarded = If((Bound(pos, 0, 4),), (Store("y", A("o"), Load("x", pos)),))
    p = program([Loop("o", 4, (Loop("k", 3, (guarded,)),), parallel=True)])
    (outer,) = unroll(p, level=1).kernels[0].body
    first, middle, last = outer.body
    assert first == If((Bound(A("o") - 1, 0, None),), (Store("y", A("o"), Load("x", A("o") - 1)),))
    assert middle == Store("y", A("o"), Load("x", A("o")))
    assert last == If((Bound(A("o") + 1, None, 4),), (Store("y", A("o"), Load("x", A("o") + 1)),))


def test_verifier_checks_indices_against_buffers_loop_kinds_and_lanes():
    inside = program([Loop("c", 8, (Store("y", A("c"), Load("x", A("c"))),), parallel=True)], size=8)
    assert verify_program(inside) == []
    beyond = program([Loop("c", 9, (Store("y", A("c"), Load("x", A("c") + 1)),), parallel=True)], size=8)
    problems = verify_program(beyond)
    assert any("x[c + 1] reaches [1, 10) outside its 8 elements" in p for p in problems)
    assert any("y[c] reaches [0, 9) outside its 8 elements" in p for p in problems)
    guarded = program(
        [Loop("c", 9, (If((Bound(A("c"), None, 8),), (Store("y", A("c"), Load("x", A("c"))),)),))], size=8
    )
    assert verify_program(guarded) == []  # the border check keeps the access in
    odd = program([Loop("c", 8, (Store("y", A("c"), Load("x", A("c"))),), lanes=3)], size=8)
    assert any("has 3 lanes" in p for p in verify_program(odd))
    with pytest.raises(ValueError, match="Loop.kind is 'vectorised', not one of"):
        Loop("c", 8, (), kind="vectorised")
