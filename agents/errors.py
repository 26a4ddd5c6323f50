"""Errors that reach the user as one line and a non-zero exit, never a traceback."""


class UserError(Exception):
    """A bad file, flag or world: the CLI prints ``wiremap: <message>`` and exits 2."""


#: Exit status of a command stopped by Ctrl-C or SIGTERM (the shell's 128 + SIGINT). ``wiremap
#: map`` and ``wiremap run`` first write what they have (``"interrupted": true`` in their
#: report) and say so on a line of its own; services (robot, fuse, router, watch) treat a signal
#: as their normal stop and exit 0.
INTERRUPTED = 130
