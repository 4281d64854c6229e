"""onnxruntime as the opponent: batch 1, one intra-op thread, all graph optimisations; timed with
inputs and outputs pre-bound (IOBinding, no Python conversion) and through plain `run`."""

from __future__ import annotations

import time

import numpy as np
import onnx

from ..verify import reference_session

THREADS = 1  # intra-op threads: the generated C runs on one core


class OnnxruntimeTimer:
    def __init__(self, model: onnx.ModelProto, input_names: list[str], inputs: list[np.ndarray]):
        import onnxruntime as ort  # only benchmarking needs it at import time

        self.version = ort.__version__
        self.model = model
        options = ort.SessionOptions()
        options.intra_op_num_threads = THREADS
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        options.log_severity_level = 3
        self.session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
        self.feed = {name: _fed(x) for name, x in zip(input_names, inputs)}
        self.binding = self.session.io_binding()
        for name, array in self.feed.items():
            self.binding.bind_ortvalue_input(name, ort.OrtValue.ortvalue_from_numpy(array))
        for out in self.session.get_outputs():
            self.binding.bind_output(out.name, "cpu")
        self.session.run_with_iobinding(self.binding)  # allocates the outputs once; later runs reuse them

    def run_bound(self, calls: int) -> float:
        """Seconds for `calls` inferences with pre-bound inputs and outputs."""
        session, binding = self.session, self.binding
        start = time.perf_counter()
        for _ in range(calls):
            session.run_with_iobinding(binding)
        return time.perf_counter() - start

    def run_plain(self, calls: int) -> float:
        """Seconds for `calls` InferenceSession.run calls: what a Python user pays."""
        session, feed = self.session, self.feed
        start = time.perf_counter()
        for _ in range(calls):
            session.run(None, feed)
        return time.perf_counter() - start

    def outputs(self) -> list[np.ndarray]:
        """The reference outputs the error columns compare with: the timed session keeps onnxruntime's
        defaults (what its users get), whose uint8 x int8 kernels saturate on x86 without VNNI."""
        return [np.asarray(x) for x in reference_session(self.model).run(None, self.feed)]


def _fed(x: np.ndarray) -> np.ndarray:
    """An input as onnxruntime takes it: integers (quantized inputs) as they are, anything else float32."""
    x = np.asarray(x)
    return np.ascontiguousarray(x, dtype=None if x.dtype.kind in "iu" else np.float32)
