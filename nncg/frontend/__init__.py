"""ONNX front end, stage 1 of the pipeline: ONNX model -> graph IR (nncg.ir.graph.Graph)."""

from nncg.frontend.importer import import_onnx
from nncg.frontend.load import load_model

__all__ = ["import_onnx", "load_model"]
