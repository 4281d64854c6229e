"""A differential fuzzer of NNCG: random valid CNN graphs compiled with random options for every
host target, built, run and compared with onnxruntime; failures shrunk and saved (`python -m nncg.fuzz`)."""
