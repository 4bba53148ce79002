"""Keep the memory a frame frees inside the process, so the next frame reuses its pages.

Each frame of the detector allocates and frees the same large arrays (about 7 MB of moved
sweeps at 114k points a sweep, tens of MB of feature maps). glibc's malloc hands blocks over
its mmap threshold (dynamic, at most 32 MB) back to the kernel when they are freed, and trims
the top of its heap, so the next frame takes fresh pages and faults each one in: about 4,000
page faults a frame at 114k points, measured. In a virtual machine a page the guest has never
touched before costs far more (28 MB took 169 ms the first time and 1.5 ms after, measured on
the development machine), which showed as 30-60 ms stalls in the node's sweep stage every
few seconds.

:func:`keep_freed_memory` asks glibc for one arena and no mmap of its own, and never to trim:
the process's heap grows to its largest frame (the warm-up reaches it) and stays there,
reused frame after frame with no page fault. The price is that memory once used stays with
the process (its resident size is its peak, not its current need), which is what a node that
runs one model at sensor rate wants. Set ``SUIT_ROS_MALLOC=default`` in the environment to
leave the allocator as it is.
"""
from __future__ import annotations

import ctypes
import os
import sys

ENV = 'SUIT_ROS_MALLOC'

# mallopt parameters (glibc malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
M_ARENA_MAX = -8


def keep_freed_memory() -> bool:
    """Configure glibc's malloc as described above; :return: whether it was done (False on
    another libc or OS, or when ``SUIT_ROS_MALLOC=default``). Call it before the threads
    that allocate start (arenas already made stay)."""
    if os.environ.get(ENV, '') == 'default' or not sys.platform.startswith('linux'):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):        # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    # the largest value glibc takes for the trim threshold is a C int
    return all(mallopt(param, value) == 1 for param, value in (
        (M_ARENA_MAX, 1), (M_MMAP_MAX, 0), (M_TRIM_THRESHOLD, 2**31 - 1)))
