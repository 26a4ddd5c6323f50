"""The wireframe mapping algorithm (pure, deterministic, no I/O).

See ``../shared/paper/wireframe-mapping.md``. Randomness is always an explicit
``numpy.random.Generator`` argument.
"""

from mapping.merge import MergeConfig, merge, merge_all, normalize
from mapping.se2 import Pose, wrap_angle
from mapping.wireframe import Label, Wireframe, paper_storage_bytes

__all__ = [
    "Label",
    "MergeConfig",
    "Pose",
    "Wireframe",
    "merge",
    "merge_all",
    "normalize",
    "paper_storage_bytes",
    "wrap_angle",
]
