"""Errors a user can act on. The CLI prints them as one line and exits with status 2."""


class NncgError(Exception):
    """Bad input or an unsupported model: the message says what is wrong and how to fix it."""


class UnsupportedOpsError(NncgError):
    """The model uses operators NNCG cannot compile; lists every one of them at once."""
