"""The fleet on the bus: key expressions and sessions (:mod:`~agents.fleet.bus`), the robot agent
(:mod:`~agents.fleet.robot`), the fusion service (:mod:`agents.fleet.fusion`), credentials
(:mod:`~agents.fleet.secure`) and child-process plumbing (:mod:`~agents.fleet.proc`)."""
