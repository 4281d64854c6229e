"""NNCG: compiles a trained CNN given as ONNX into one plain C file and header.

Pipeline: ONNX -> graph IR (nncg.frontend) -> graph passes -> loop-nest IR (nncg.lowering) ->
loop passes (nncg.passes) -> C (nncg.backends)."""

__version__ = "0.1.0"

from .backends import get_target  # noqa: E402
from .compiler import CompiledModel, compile, emit  # noqa: E402
from .errors import NncgError, NncgWarning  # noqa: E402
from .frontend import import_onnx, load_model  # noqa: E402
from .options import CompileOptions  # noqa: E402
from .passes import PassManager, default_pipeline  # noqa: E402
from .quantization import quantize  # noqa: E402

__all__ = [
    "CompileOptions",
    "CompiledModel",
    "NncgError",
    "NncgWarning",
    "PassManager",
    "compile",
    "default_pipeline",
    "emit",
    "get_target",
    "import_onnx",
    "load_model",
    "quantize",
]
