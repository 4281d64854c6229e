"""--verify on quantised models (issue 16): their outputs are judged in quantisation steps, by the one
rule the int8 tests and benchmark use (nncg/quant_steps.py): a DequantizeLinear's output in steps of
its scale (per channel where the scale is), a QuantizeLinear's or QLinear operator's integers in steps
of 1; max steps and the share of bit-identical elements are printed, and an output passes within one
step. Float outputs keep the relative tolerance; an int32 output (ConvInteger) is still exact."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from helpers import nncg_onnx
from int8_models import quantized, repository_model
from onnx import TensorProto, helper, numpy_helper
from test_int8_io import qdq_conv_model, qlinear_conv_model

import nncg
from nncg.errors import NncgError
from nncg.quant_steps import Step, compare_steps, tensor_steps
from nncg.report import Measurements, write_report
from nncg.verify import ErrorStat, VerifyReport, compare, verify
from nncg.verify_layers import LayerReport, LayerStat

SCALE = np.float32(0.05)


def _dequantized_output_model(scale, axis: int = 1) -> onnx.ModelProto:
    """x (float) -> QuantizeLinear -> DequantizeLinear (scale per tensor or per channel) -> Flatten -> y."""
    per_channel = np.ndim(scale) == 1
    nodes = [
        helper.make_node("QuantizeLinear", ["x", "s", "z"], ["q"], **({"axis": axis} if per_channel else {})),
        helper.make_node("DequantizeLinear", ["q", "s", "z"], ["d"], **({"axis": axis} if per_channel else {})),
        helper.make_node("Flatten", ["d"], ["y"]),
    ]
    zero = np.zeros(np.shape(scale), np.uint8)
    graph = helper.make_graph(
        nodes,
        "steps",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 2, 2])],
        [
            helper.make_tensor_value_info("d", TensorProto.FLOAT, None),
            helper.make_tensor_value_info("y", TensorProto.FLOAT, None),
        ],
        [numpy_helper.from_array(np.asarray(scale, np.float32), "s"), numpy_helper.from_array(zero, "z")],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def test_steps_of_dequantized_integer_and_moved_tensors():
    steps = tensor_steps(_dequantized_output_model(SCALE))
    assert set(steps) == {"q", "d", "y"}
    assert float(steps["q"].scale) == 1.0 and float(steps["d"].scale) == SCALE and float(steps["y"].scale) == SCALE
    per_channel = tensor_steps(_dequantized_output_model(np.array([0.1, 0.2, 0.4], np.float32)))
    assert per_channel["d"].per_element(4).shape == (3, 1, 1)
    assert "y" not in per_channel  # Flatten moves a per-channel axis: no step claimed


def test_compare_counts_steps_per_channel():
    model = _dequantized_output_model(np.array([0.1, 0.2, 0.4], np.float32))
    ref = np.zeros((1, 3, 2, 2), np.float32)
    ours = ref.copy()
    ours[0, 2, 0, 0] = np.float32(0.4)  # one step of channel 2
    ours[0, 0, 1, 1] = np.float32(0.1)  # one step of channel 0
    (stat,) = compare([ours], [ref], ["d"], tensor_steps(model))
    assert stat.max_steps == pytest.approx(1.0) and stat.identical == 10 / 12 and stat.passes(1e-4)
    ours[0, 0, 1, 1] = np.float32(0.2)  # two steps of channel 0, less than one of channel 2
    (stat,) = compare([ours], [ref], ["d"], tensor_steps(model))
    assert stat.max_steps == pytest.approx(2.0) and not stat.passes(1e-4)
    with pytest.raises(NncgError, match="output 'y' has no quantisation step"):
        compare_steps(model, [([ours, ours.reshape(1, 12)], [ref, ref.reshape(1, 12)])])
    per_tensor = _dequantized_output_model(SCALE)
    ours = ref.copy()
    ours[0, 1, 0, 1] = 2 * SCALE
    comparison = compare_steps(per_tensor, [([ours, ours.reshape(1, 12)], [ref, ref.reshape(1, 12)])])
    assert comparison.max_steps == pytest.approx(2.0) and comparison.identical == 22 / 24


def test_integer_outputs_with_a_step_may_differ_by_one_int32_sums_may_not():
    steps = {"q": Step(np.array(1.0))}
    ref = np.array([[3, 200]], np.uint8)
    one_off, two_off = np.array([[4, 200]], np.uint8), np.array([[3, 202]], np.uint8)
    assert compare([one_off], [ref], ["q"], steps)[0].passes(1e-4)
    assert not compare([two_off], [ref], ["q"], steps)[0].passes(1e-4)
    int32 = compare([one_off.astype(np.int32)], [ref.astype(np.int32)], ["sum"], steps)[0]
    assert int32.problem is not None and not int32.passes(1e-4)
    mixed = compare([one_off.astype(np.float32)], [ref], ["q"], steps)[0]
    assert mixed.problem == "float32 output where the reference is uint8"


def test_report_prints_steps_and_the_rule(tmp_path):
    quantised = ErrorStat("probabilities", (1, 2), 0.0039, 0.0075, max_steps=1.0, identical=0.5)
    report = VerifyReport("net", "ansi-c", (quantised,), 1e-4, 0)
    lines = report.format().splitlines()
    assert lines[1].split() == [
        "output",
        "shape",
        "max",
        "abs",
        "err",
        "max",
        "rel",
        "err",
        "max",
        "steps",
        "identical",
    ]
    assert lines[2].split()[-3:] == ["1", "50.00", "%"]
    assert lines[-1] == "PASS: quantised outputs within 1 quantisation step of onnxruntime's required"
    two = VerifyReport("net", "ansi-c", (quantised, ErrorStat("logits", (1, 2), 1.0, 0.5)), 1e-4, 0)
    assert two.format().splitlines()[-1] == (
        "FAIL: quantised outputs within 1 quantisation step of onnxruntime's, others max rel err <= 0.0001 required"
    )
    layer = LayerStat((("conv", "QLinearConv"),), ErrorStat("c", (1, 4), 2.0, 0.1, max_steps=2.0, identical=0.75))
    text = LayerReport("net", "ansi-c", (layer,), 1e-4, 0).format()
    assert text.endswith("FAIL: first layer above tolerance: conv (QLinearConv), tensor c: max steps 2 > 1")
    compiled = nncg.compile(qlinear_conv_model())
    write_report(compiled, tmp_path, Measurements(verify=report))
    markdown = (tmp_path / f"{compiled.name}.report.md").read_text()
    assert "| max steps | identical |" in markdown and "quantised outputs within 1 quantisation step" in markdown


@pytest.mark.parametrize(
    "model", [qlinear_conv_model(np.int8, np.int8), qdq_conv_model(np.uint8)], ids=["qlinear", "qdq"]
)
def test_integer_io_models_are_verified_in_steps(model):
    report = verify(model, nncg.compile(model, target="ansi-c"))
    (stat,) = report.stats
    assert stat.quantized and stat.max_steps == 0 and stat.identical == 1.0 and report.ok, report.format()


def test_cli_verifies_the_int8_mobilenet_in_steps(tmp_path):
    """The int8 mobilenet's probabilities (steps of 1/255) are one step off onnxruntime
    for the seed-0 input: over the float rule's 1e-4, within the int8 rule's one step."""
    path = tmp_path / "mobilenet_int8.onnx"
    onnx.save(quantized(repository_model("benchmarks/models/mobilenet_v1_025.onnx"), "int8"), path)
    result = nncg_onnx(path, "--target", "ansi-c", "-o", tmp_path / "out", "--verify")
    assert result.returncode == 0, result.stderr + result.stdout
    header, row = result.stdout.splitlines()[2:4]
    assert header.split()[-3:] == ["max", "steps", "identical"]
    cells = row.split()
    assert float(cells[4]) > 1e-4 and cells[5:] == ["1", "50.00", "%"], row
    assert "PASS: quantised outputs within 1 quantisation step of onnxruntime's required" in result.stdout
