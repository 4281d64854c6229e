"""Benchmarking: NNCG against onnxruntime and against the hardware limit."""
