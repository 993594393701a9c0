"""CPU memory reuse for training processes.

An update at the CPU default sizes allocates temporaries of one to two megabytes (a critic
layer's output over every rollout state is ``[K, B (1 + N H), cells]`` floats). glibc's
malloc may serve blocks of that size with ``mmap`` and hand freed memory at the top of the
heap back to the kernel, so that the next update faults the same pages in again. Whether it
does depends on the process's history: glibc raises its thresholds after freeing a mapped
block, and in the recipe's processes that usually happens early. In a fresh process it did
not: a RAVE update took about 2,300 page faults and 1.2x as long
(``benchmarks/malloc_reuse.py``). ``keep_freed_memory`` sets the thresholds once, so no
process depends on that history. Arithmetic is untouched: results are bit-for-bit the same.

It changes the whole process's allocator, so the library never calls it on import; the
recipe does (``keep_freed_memory: true`` in its config), and so can any training script.
"""

from __future__ import annotations

import ctypes
import sys

# mallopt parameters, from glibc's <malloc.h>
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
# glibc's largest allowed mmap threshold on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX): blocks up
# to this size come from the heap and are reused; larger ones are still mapped and unmapped
MMAP_THRESHOLD_MAX = 32 * 1024 * 1024


def keep_freed_memory() -> bool:
    """Have glibc's malloc reuse freed blocks of up to 32 MiB instead of returning them to
    the kernel (no ``mmap`` below that size, no trimming of the heap). The process keeps
    its peak heap size for its lifetime.

    Returns whether the setting took effect: ``False`` off glibc (macOS, Windows, musl),
    where nothing is changed.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)  # the C library this process already runs on
    except OSError:
        return False
    mallopt = getattr(libc, "mallopt", None)
    gnu_version = getattr(libc, "gnu_get_libc_version", None)
    if mallopt is None or gnu_version is None:  # not glibc
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    # -1 turns trimming off altogether (mallopt(3)); both calls return 1 on success
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX)) and bool(
        mallopt(M_TRIM_THRESHOLD, -1)
    )
