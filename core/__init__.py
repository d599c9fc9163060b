"""lightstage: raw light-stage captures to relightable neural models of translucent objects.

The root package holds what every stage shares: user-facing errors, atomic writes, thread control and
the conventions (cameras, lights, tonemap), each defined in exactly one module.
"""

from lightstage.errors import LightstageError
from lightstage.threads import bound_openmp_spin

bound_openmp_spin()  # before anything imports torch (lightstage.threads)

__version__ = "0.1.0"
__all__ = ["LightstageError", "__version__"]
