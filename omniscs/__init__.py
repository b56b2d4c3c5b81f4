"""OmniSCS: safety-critical driving scenarios from ordinary logs (domain library, free of Prefect)."""
import os as _os

# torch and the rasterizer's Numba kernels each run an OpenMP thread pool; with the default (spinning)
# wait policy the two pools busy-wait against each other and every small torch op after a Numba kernel
# runs 5-10x slower on a 2-core machine. Idle OpenMP threads must sleep. Read when OpenMP starts, so it
# is set here, before anything imports torch or numba; a value the user set is kept.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
