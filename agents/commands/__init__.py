"""One module per ``wiremap`` subcommand; each exposes ``HELP``, ``add_arguments(parser)`` and
``run(args) -> int``. ``agents.cli`` imports only the module of the command that runs."""
