"""Back-end plugins: they own the factor graph and never see point clouds.

``isam2`` (default) optimises incrementally after every keyframe; ``batch`` collects
everything and runs Levenberg-Marquardt once in ``finalize``. Both implement
:class:`slam.backend.Backend`.
"""

from backends.batch import BatchBackend
from backends.isam2 import Isam2Backend

__all__ = ["BatchBackend", "Isam2Backend"]
