"""The test session's reaper of Ray workers that outlive their cluster (tests/conftest.py)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import reap_ray_workers

pytestmark = pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs /proc (Linux)")


def _sleeper(raylet: str) -> subprocess.Popen:
    env = {**os.environ, "RAY_RAYLET_PID": raylet}
    return subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], env=env)


def test_reaper_kills_only_the_workers_of_the_given_raylets() -> None:
    ours, other = _sleeper("999991"), _sleeper("999992")
    try:
        time.sleep(0.5)  # the children's environ is readable once they run
        killed = reap_ray_workers({999991})
        assert ours.pid in killed and other.pid not in killed
        assert ours.wait(timeout=10) != 0
        assert other.poll() is None
        assert reap_ray_workers(set()) == []
    finally:
        for process in (ours, other):
            process.kill()
            process.wait()
