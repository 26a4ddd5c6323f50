"""``wiremap bench <name>``: one module per benchmark (``HELP``, ``add_arguments``, ``run``).

Benchmarks print a table on stderr-free stdout followed by one JSON object on its own last line
(with ``--json``), so scripts can take ``tail -n 1``.
"""
