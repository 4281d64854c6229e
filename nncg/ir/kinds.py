"""The closed vocabularies of both IRs as enums: loop kinds, operators, comparisons, data types,
buffer roles and layouts, activation kinds and GELU approximations, conv algorithms and vector axes. Each member is
also its text (it compares, hashes, prints and formats as its value), so IR text and generated C
spell them as before, and IR nodes built from text are converted on construction: a misspelt kind
fails where it is made."""

from __future__ import annotations

from enum import Enum


class TextEnum(str, Enum):
    """A str-valued enum that behaves as its value everywhere a string is used."""

    def __str__(self) -> str:
        return str.__str__(self)

    def __format__(self, spec: str) -> str:
        return str.__format__(str.__str__(self), spec)

    __hash__ = str.__hash__


class LoopKind(TextEnum):
    """A pass's mark on a loop, which the same or a later pass materialises; only serial loops remain."""

    SERIAL = "serial"
    UNROLLED = "unrolled"
    VECTORIZED = "vectorized"


class BinaryOp(TextEnum):
    ADD = "+"
    SUB = "-"
    MUL = "*"
    DIV = "/"
    MAX = "max"
    MIN = "min"


class Comparison(TextEnum):
    GT = ">"
    GE = ">="
    LT = "<"
    LE = "<="


class MathFunction(TextEnum):
    """The math functions kernels call: math.h's (C89, double) in scalar code, where sigmoid is
    1 / (1 + exp(-x)), abs is fabs, and erf and softplus, which C89 lacks, are helpers
    (backends/scalar_math.py); on vectors polynomial approximations, the sqrt instruction and a
    sign mask (backends/vector_math.py)."""

    EXP = "exp"
    LOG = "log"
    TANH = "tanh"
    SIGMOID = "sigmoid"
    ERF = "erf"
    ABS = "abs"
    SQRT = "sqrt"
    SOFTPLUS = "softplus"  # log(1 + exp(x))


class DType(TextEnum):
    """The element type of a graph value, a buffer or an expression. float64 is for expressions only
    (exact products of small integers and float32 scales, see lowering/quantized_add.py)."""

    FLOAT32 = "float32"
    FLOAT64 = "float64"
    INT8 = "int8"
    UINT8 = "uint8"
    INT16 = "int16"
    INT32 = "int32"

    @property
    def is_integer(self) -> bool:
        return self.value.startswith(("int", "uint"))

    @property
    def bytes(self) -> int:
        return {"float32": 4, "float64": 8, "int8": 1, "uint8": 1, "int16": 2, "int32": 4}[self.value]

    @property
    def range(self) -> tuple[int, int]:
        """The smallest and largest value of an integer type."""
        bits = self.bytes * 8
        return (0, 2**bits - 1) if self.value.startswith("uint") else (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)


class BufferRole(TextEnum):
    INPUT = "input"
    OUTPUT = "output"
    INTERNAL = "internal"
    CONSTANT = "constant"


class Layout(TextEnum):
    """How a buffer orders a tensor's dims: row-major as in ONNX (NCHW: planar), or channels last."""

    UNSPECIFIED = ""
    ROW_MAJOR = "row-major"
    CHANNELS_LAST = "channels-last"


class ActivationKind(TextEnum):
    RELU = "relu"
    LEAKY_RELU = "leaky_relu"
    CLIP = "clip"
    SIGMOID = "sigmoid"
    TANH = "tanh"
    HARD_SIGMOID = "hard_sigmoid"
    HARD_SWISH = "hard_swish"
    ELU = "elu"
    SILU = "silu"
    ERF = "erf"
    GELU = "gelu"
    ABS = "abs"
    NEG = "neg"
    SQRT = "sqrt"
    EXP = "exp"
    LOG = "log"
    RECIPROCAL = "reciprocal"
    POW = "pow"
    SOFTPLUS = "softplus"
    SOFTSIGN = "softsign"
    MISH = "mish"
    SELU = "selu"
    CELU = "celu"
    THRESHOLDED_RELU = "thresholded_relu"


class GeluApproximation(TextEnum):
    """How a gelu activation computes x * Phi(x): exactly, with erf, or with ONNX's (and torch's) tanh
    approximation."""

    NONE = "none"
    TANH = "tanh"


class ConvAlgorithm(TextEnum):
    DIRECT = "direct"
    WINOGRAD = "winograd"


class VectorAxis(TextEnum):
    """What a Conv's SIMD runs over: output channels (channels-last output) or output pixels (a
    planar output, its rows vectorised). Decided once, by the vectorize-pixels pass."""

    CHANNELS = "channels"
    PIXELS = "pixels"


def coerce(instance: object, **kinds: type[TextEnum]) -> None:
    """In a frozen dataclass's __post_init__: each named field converted to its enum (ValueError names
    the field and the values it takes)."""
    for field_name, kind in kinds.items():
        value = getattr(instance, field_name)
        if isinstance(value, kind):
            continue
        try:
            object.__setattr__(instance, field_name, kind(value))
        except ValueError:
            allowed = ", ".join(repr(m.value) for m in kind)
            raise ValueError(f"{type(instance).__name__}.{field_name} is {value!r}, not one of {allowed}") from None
