"""The node's allocator setting (suit_ros.heap), in fresh processes: it changes the whole
process's malloc."""
import subprocess
import sys

import pytest

PROBE = '''
import resource, sys
from suit_ros.heap import keep_freed_memory
done = keep_freed_memory()
import numpy as np
np.core.multiarray._set_madvise_hugepage(False)    # 4 KB pages, as torch's tensors get
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
a = np.ones(48 * 2**20 // 8); del a            # a frame's large array, freed
before = faults()
b = np.ones(48 * 2**20 // 8); del b            # the next frame's
print(done, faults() - before)
'''


def run_probe(**env: str) -> tuple[bool, int]:
    import os
    out = subprocess.run([sys.executable, '-c', PROBE], capture_output=True, text=True,
                         check=True, env={**os.environ, **env}).stdout.split()
    return out[0] == 'True', int(out[1])


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='glibc malloc')
def test_freed_memory_is_reused_without_page_faults():
    """A 48 MB array freed and allocated again: with the setting, the second one reuses the
    pages (no fault for each of its 12k pages); glibc's own behaviour (SUIT_ROS_MALLOC=default)
    hands them back to the kernel and faults every page in again."""
    kept, kept_faults = run_probe()
    default, default_faults = run_probe(SUIT_ROS_MALLOC='default')
    assert kept and not default
    assert kept_faults < 500
    assert default_faults > 10_000
