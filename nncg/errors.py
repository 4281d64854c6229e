"""Errors a user can act on. The CLI prints them as one line and exits with status 2."""

from .safe_text import terminal_line


class NncgError(Exception):
    """Bad input or an unsupported model: the message says what is wrong and how to fix it. It is
    one printable line whatever outside text it quotes (see safe_text.terminal_line)."""

    def __init__(self, message: object = ""):
        super().__init__(terminal_line(str(message)))


class UnsupportedOpsError(NncgError):
    """The model uses operators NNCG cannot compile; lists every one of them at once."""


class NncgWarning(UserWarning):
    """A default NNCG chose for the user (e.g. batch 1 for a dynamic batch dimension); the message says
    how to choose otherwise. The CLI prints it as one note line on stderr."""
