from agents.fleet.fusion.service import *  # noqa: F403  (temporary, split in progress)
