"""C identifiers for outside names (tensors, layers, --name): valid C, never a keyword, never a name that
standard, POSIX or intrinsics headers define or reserve, never one of the generated API's own names.
Every identifier in generated C is made here; renaming is deterministic (same names, same result)."""

from __future__ import annotations

import hashlib
import re
from collections.abc import Callable
from functools import cache
from importlib import resources

MAX_LENGTH = 63  # significant characters of an internal identifier that C99 guarantees

KEYWORDS = frozenset(
    # C89 .. C23
    """auto break case char const continue default do double else enum extern float for goto if int
    long register return short signed sizeof static struct switch typedef union unsigned void volatile
    while inline restrict bool true false alignas alignof constexpr nullptr static_assert thread_local
    typeof typeof_unqual noreturn complex imaginary main"""
    # C++ (the header is `extern "C"` for C++ callers, so its parameter names must be C++-safe too)
    """ and and_eq asm bitand bitor catch char8_t char16_t char32_t class co_await co_return co_yield
    compl concept const_cast consteval constinit decltype delete dynamic_cast explicit export friend
    mutable namespace new noexcept not not_eq operator or or_eq private protected public
    reinterpret_cast requires static_cast template this throw try typeid typename using virtual
    wchar_t xor xor_eq"""
    # macros of common platform headers (windows.h's min/max, rpcndr.h's small and hyper)
    """ min max near far small hyper pascal cdecl IN OUT OPTIONAL""".split()
)

# Names the C standard reserves for future library use, POSIX's _t, the intrinsics headers'
# spellings: a name matching one may be defined by some other C library.
RESERVED_PATTERNS = re.compile(
    r"""E[0-9A-Z]\w*|(is|to|str|mem|wcs|cnd_|mtx_|thrd_|tss_|atomic_|memory_order_)[a-z]\w*
    |(LC_|SIG_?|FE_|FP_|MATH_|PRI|SCN|FLT_|DBL_|LDBL_|INT|UINT|WINT_|WCHAR_|SIZE_|PTRDIFF_|SIG_ATOMIC_)[A-Z0-9]\w*
    |\w*_t|\w*_(MAX|MIN|C|WIDTH)|v\w*_[bfpsu](8|16|32|64)(x\d+)*""",
    re.X,
)

# What the generated code defines besides the model's names: the header's portability macros, the
# run functions' parameters and the profile build's locals.
GENERATED = frozenset({"arena", "weights", "start", "end"})
GENERATED_PREFIX = "nncg_"  # NNCG_ALIGNED, NNCG_RESTRICT, nncg_now, the test harnesses' names

# NAME_<suffix> are the API's functions and objects, NAMEU_<SUFFIX> its macros (NAMEU = NAME upper-cased):
# a layer's function NAME_<layer> must not be one of them.
API_SUFFIXES = frozenset(
    """run arena weights_ok profile_count profile_layers profile_seconds
    h arena_bytes arena_align weights_bytes weights_align weights_crc32""".split()
)


@cache
def _standard_names() -> frozenset[str]:
    text = resources.files(__package__).joinpath("reserved_c_names.txt").read_text()
    return frozenset(line for line in text.split() if not line.startswith("#"))


def is_reserved(ident: str) -> bool:
    """Whether `ident` is a keyword or may be defined by a standard, POSIX or intrinsics header."""
    return (
        ident in KEYWORDS
        or ident.startswith("_")
        or ident in _standard_names()
        or RESERVED_PATTERNS.fullmatch(ident) is not None
    )


def c_identifier(name: str, limit: int | None = MAX_LENGTH) -> str:
    """A valid, unreserved C identifier resembling `name`: runs of other characters become `_`, at most
    `limit` characters (a long name keeps its head and a hash of the whole), a reserved result
    gets a `t_` prefix (and a `_` suffix when still reserved). Callers make it unique."""
    trimmed = re.sub(r"^[^A-Za-z0-9_]+|[^A-Za-z0-9_]+$", "", name)  # `/conv1/Conv` -> `conv1_Conv`
    ident = re.sub(r"[^A-Za-z0-9_]+", "_", trimmed).lstrip("_") or "t"
    if limit is not None and len(ident) > limit:
        digest = hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:8]
        ident = f"{ident[: limit - 11].rstrip('_')}_{digest}"
    if ident[0].isdigit() or is_reserved(ident):
        ident = "t_" + ident
    if is_reserved(ident):
        ident += "_"
    return ident


def program_name(name: str) -> str:
    """The C name of the generated function from `--name` or the model's name: an identifier whose
    API names (NAME_run, NAMEU_ARENA_BYTES, ...) are not reserved either. Not shortened: the user
    chose it (a name too long for a file name is refused when the files are written)."""
    ident = c_identifier(name, limit=None)
    if ident in GENERATED or ident.lower().startswith(GENERATED_PREFIX) or any(map(is_reserved, _api_probes(ident))):
        ident = c_identifier("t_" + ident, limit=None)
    return ident


def _api_probes(name: str) -> tuple[str, ...]:
    upper = name.upper()
    return (name, f"{name}_run", f"{upper}_H", f"{upper}_ARENA_BYTES", f"{upper}_X_SIZE")


def layer_name(name: str) -> str:
    """A layer's C name (its function is NAME_<layer>): an identifier that is not an API suffix."""
    ident = c_identifier(name)
    lower = ident.lower()
    if lower in API_SUFFIXES or lower.endswith("_size"):
        ident += "_layer"
    return ident


def is_model_name(ident: str, program: str) -> bool:
    """Whether a buffer or local named `ident` could collide with the generated API of `program`:
    its functions and macros (all start with NAME_ or NAMEU_), the fixed names and nncg_*."""
    lower, prefix = ident.lower(), program.lower()
    return lower == prefix or lower.startswith(prefix + "_") or lower.startswith(GENERATED_PREFIX) or ident in GENERATED


def buffer_name(name: str, program: str) -> str:
    """A tensor's C name in the program `program`: an identifier outside the generated API's names
    (a tensor called `arena` or `robot_run` gets a prefix; two prefixes, as one may be the program's)."""
    ident = c_identifier(name)
    for candidate in (ident, "t_" + ident, "x_" + ident):
        if not is_model_name(candidate, program) and not is_reserved(candidate):
            return candidate
    raise AssertionError(f"no C name for {ident!r} next to {program!r}")  # t_ and x_ cannot both clash


class Namespace:
    """Hands out distinct identifiers, ignoring case (the header derives upper-case macro names from
    them): `make` turns a wanted name into a valid one, `taken` says what else is off limits."""

    def __init__(self, make: Callable[[str], str] = c_identifier, taken: Callable[[str], bool] = lambda ident: False):
        self._make, self._taken = make, taken
        self._used: set[str] = set()

    def claim(self, name: str) -> str:
        base = self._make(name)
        ident, i = base, 1
        while ident.lower() in self._used or self._taken(ident) or is_reserved(ident):
            ident, i = f"{base}_{i}", i + 1
        self._used.add(ident.lower())
        return ident
