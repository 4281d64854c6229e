"""Real-size benchmark models: torchvision architectures (benchmarks/torch_models.py) exported to ONNX,
a Keras-style NHWC model with tf2onnx's transposes (benchmarks/nhwc_model.py) and the four MLPerf Tiny
reference models through Keras -> TFLite -> tf2onnx (benchmarks/mlperf_tiny.py).

    python3 -m benchmarks.real_models [--models resnet18 ...] [--size 96]

writes benchmarks/models/real/<name>_<size>.onnx (the default cases without --size) and checks each in
onnxruntime. The MLPerf Tiny models have their own fixed input size (--size leaves them at it) and are
written as <name>.onnx; they need TensorFlow and tf2onnx (the `keras` extra). The exports are deterministic
(fixed seed, TorchScript exporter, fixed opset and input shape; see mlperf_tiny.py for tf2onnx's), so
the files are not committed: they are tens of MB, and the suite exports the ones it needs when missing. Torch
comes with the `bench` extra (pip install -e .[bench]).
"""

from __future__ import annotations

import argparse
import io
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort

from . import mlperf_tiny
from .nhwc_model import NAME as NHWC
from .nhwc_model import keras_mobilenet_nhwc

OPSET = 17
SEED = 0
ROOT = Path(__file__).resolve().parent.parent
REAL_DIR = ROOT / "benchmarks" / "models" / "real"
ARCHITECTURES = [
    "mobilenet_v2", "mobilenet_v3_small", "resnet18", "efficientnet_b0", "squeezenet1_1", "shufflenet_v2_x0_5",
    "mnasnet0_5", "regnet_x_400mf",
]  # fmt: skip
RESIZABLE = [*ARCHITECTURES, NHWC]
# Models with their own fixed input size (their case's size is None): --size does not apply to them.
FIXED_SIZE = mlperf_tiny.MODELS
MODELS = [*RESIZABLE, *FIXED_SIZE]
# Every resizable model at 96x96 (the embedded-vision size), two at ImageNet's 224x224, then the MLPerf Tiny ones.
DEFAULT_CASES = (
    [(name, 96) for name in RESIZABLE]
    + [("resnet18", 224), ("mobilenet_v2", 224)]
    + [(name, None) for name in FIXED_SIZE]
)


def cases_at(models: list[str], size: int) -> list[tuple[str, int | None]]:
    """`models` at input `size`, the fixed-size ones at their own."""
    return [(m, None if m in FIXED_SIZE else size) for m in models]


def case_name(name: str, size: int | None) -> str:
    return name if size is None else f"{name}_{size}"


def real_path(name: str, size: int | None) -> Path:
    return REAL_DIR / f"{case_name(name, size)}.onnx"


def model_bytes(name: str, size: int | None) -> bytes:
    if name in FIXED_SIZE:
        return mlperf_tiny.onnx_bytes(name)
    return keras_mobilenet_nhwc(size).SerializeToString() if name == NHWC else export_bytes(name, size)


def export_bytes(model, size: int, **options) -> bytes:
    """`model` (a torch.nn.Module, or an architecture name built with `options`) as ONNX for a
    1x3xSIZExSIZE input, through the legacy TorchScript exporter (stable, byte-identical output)."""
    import torch

    from .torch_models import build

    if isinstance(model, str):
        model = build(model, SEED, **options)
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # dynamo=False is deprecated in favour of torch.export
        torch.onnx.export(
            model, (torch.zeros(1, 3, size, size),), buffer, dynamo=False, opset_version=OPSET,
            input_names=["input"], output_names=["logits"], do_constant_folding=True,
        )  # fmt: skip
    return buffer.getvalue()


def run_in_onnxruntime(model: bytes | Path) -> np.ndarray:
    """The model's output on a fixed-seed input; raises when onnxruntime cannot load or run it."""
    source = str(model) if isinstance(model, Path) else model
    session = ort.InferenceSession(source, providers=["CPUExecutionProvider"])
    (inp,) = session.get_inputs()
    x = np.random.default_rng(0).standard_normal(inp.shape).astype(np.float32)
    return session.run(None, {inp.name: x})[0]


def ensure(name: str, size: int | None) -> Path:
    """The exported model's path, exporting (and checking in onnxruntime) when the file is missing."""
    path = real_path(name, size)
    if not path.exists():
        data = model_bytes(name, size)
        onnx.checker.check_model(onnx.load_from_string(data))
        run_in_onnxruntime(data)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    return path


def ensure_int8(name: str) -> Path:
    """The MLPerf Tiny model `name`'s full-integer TFLite conversion (a QDQ model, benchmarks/int8_suite.py),
    converted (and checked in onnxruntime) when the file is missing."""
    path = REAL_DIR / f"{name}_int8.onnx"
    if not path.exists():
        data = mlperf_tiny.onnx_bytes(name, int8=True)
        onnx.checker.check_model(onnx.load_from_string(data))
        run_in_onnxruntime(data)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", choices=MODELS, help="default: the suite's cases")
    parser.add_argument(
        "--size", type=int, help="input height and width (default: the suite's sizes; MLPerf Tiny models keep theirs)"
    )
    args = parser.parse_args(argv)
    cases = [(m, s) for m, s in DEFAULT_CASES if not args.models or m in args.models]
    if args.size:
        cases = cases_at(args.models or MODELS, args.size)
    for name, size in cases:
        real_path(name, size).unlink(missing_ok=True)  # always re-export: the script is the source of truth
        path = ensure(name, size)
        shape = list(run_in_onnxruntime(path).shape)
        print(f"{path.relative_to(ROOT)}: {path.stat().st_size:,} bytes, runs in onnxruntime, output {shape}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
