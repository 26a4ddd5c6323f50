"""Processes and I/O around the pure algorithm: simulator, robot agent, fusion service, bus,
Rerun logging and the ``wiremap`` command line."""
