"""keep_freed_memory: step-sized arrays freed and allocated again reuse their pages (no page faults)."""

import os
import platform
import subprocess
import sys

import pytest

FAULTS_PER_STEP = """
import ctypes, resource, sys
ctypes.CDLL(None).prctl(41, 1, 0, 0, 0)  # PR_SET_THP_DISABLE: 4 KiB pages whatever the kernel's THP setting
import numpy as np
from dsr_bench.memory import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
shape = (3, 128, 128, 48)
def step():  # roughly what evaluate allocates and frees each step: 9.4, 4.7, 9.4 and 3.1 MB
    flow, pred = np.ones(shape, np.float32), np.ones(shape, np.float16)
    diff, tsdf = flow - pred, np.ones(shape[1:], np.float32)
    return float(diff.sum() + tsdf.sum())
step(), step()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    step()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 5)
"""


def _faults_per_step(mode: str) -> float:
    """Minor page faults per step in a fresh process, with transparent huge pages off for it (a kernel whose THP is
    `always`, RHEL's default, faults a 9.4 MB block in 2 MiB at a time: 13 faults a step with glibc's huge-page
    tunable, under the 1,152 asserted; 6,000-6,500 with THP off) and glibc's own malloc defaults (no GLIBC_TUNABLES)."""
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    out = subprocess.run([sys.executable, "-c", FAULTS_PER_STEP, mode], capture_output=True, text=True, check=True,
                         env=env)
    return float(out.stdout)


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_freed_step_arrays_are_reused_without_page_faults():
    flow_pages = 3 * 128 * 128 * 48 * 4 // 4096
    assert _faults_per_step("default") > flow_pages / 2  # glibc maps fresh blocks: their pages fault in again
    assert _faults_per_step("keep") < 20  # the freed blocks are reused from the heap
