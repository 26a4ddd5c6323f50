"""Errors that reach the user as one line and a non-zero exit, never a traceback."""


class UserError(Exception):
    """A bad file, flag or world: the CLI prints ``wiremap: <message>`` and exits 2."""
