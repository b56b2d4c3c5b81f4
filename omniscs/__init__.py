"""OmniSCS: safety-critical driving scenarios from ordinary logs (domain library, free of Prefect)."""
import os as _os

# torch and the rasterizer's Numba kernels each run an OpenMP thread pool; with the default (spinning)
# wait policy the two pools busy-wait against each other and every small torch op after a Numba kernel
# runs 5-10x slower on a 2-core machine. Idle OpenMP threads must sleep. Read when OpenMP starts, so it
# is set here, before anything imports torch or numba; a value the user set is kept.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _keep_freed_memory() -> None:
    """Let glibc keep freed memory for the next step instead of returning it to the kernel.

    A render or fit step allocates and frees tens of megabytes of arrays; with glibc's adaptive defaults the heap
    was trimmed after every step and every array came back as fresh pages (640x360 with 100k Gaussians: 2,000-6,500
    page faults a forward+backward, measured). Arrays up to 32 MiB now stay in the heap and up to 128 MiB of free
    heap is kept. Skipped where the user tunes malloc (any ``MALLOC_*`` variable) or glibc is absent.
    """
    if any(name.startswith("MALLOC_") for name in _os.environ):
        return
    try:
        import ctypes

        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return
    m_trim_threshold, m_mmap_threshold = -1, -3
    mallopt(m_mmap_threshold, 32 << 20)
    mallopt(m_trim_threshold, 128 << 20)


_keep_freed_memory()

__version__ = "0.1.0"
