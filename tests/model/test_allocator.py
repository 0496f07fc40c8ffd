"""model/allocator.py: the process's malloc arena limit (glibc), its setting, and that it takes effect."""

from __future__ import annotations

import ctypes.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

from gradsep.model import allocator

REPO = Path(__file__).resolve().parents[2]
GLIBC = sys.platform.startswith("linux") and allocator._libc() is not None and "musl" not in str(
    ctypes.util.find_library("c"))

# Eight threads each hold small malloc blocks at the same time, then glibc's malloc_info names every arena in use.
_ARENAS_PROBE = """
import ctypes, os, sys, tempfile, threading
sys.path.insert(0, {repo!r})
from gradsep.model.allocator import configure_malloc
print("limit", configure_malloc())
barrier = threading.Barrier(8)
def work():
    blocks = [bytearray(4096) for _ in range(64)]  # PyMem -> malloc, below the mmap threshold: an arena's heap
    barrier.wait()
    barrier.wait()
threads = [threading.Thread(target=work) for _ in range(7)]
for t in threads:
    t.start()
barrier.wait()
libc = ctypes.CDLL("libc.so.6")
libc.fopen.restype = ctypes.c_void_p
path = os.path.join(tempfile.mkdtemp(), "malloc.xml")
stream = libc.fopen(path.encode(), b"w")
libc.malloc_info(0, ctypes.c_void_p(stream))
libc.fclose(ctypes.c_void_p(stream))
barrier.wait()
print("arenas", open(path).read().count("<heap nr="))
"""


def _arenas_in_use(env: dict[str, str]) -> tuple[str, int]:
    out = subprocess.run([sys.executable, "-c", _ARENAS_PROBE.format(repo=str(REPO))], env=env, check=True,
                         capture_output=True, text=True, timeout=120).stdout.split("\n")
    limit = next(line for line in out if line.startswith("limit")).split()[1]
    return limit, int(next(line for line in out if line.startswith("arenas")).split()[1])


def _env(**values: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("MALLOC_ARENA_MAX", allocator.ARENAS_ENV)}
    return env | values


@pytest.mark.skipif(not GLIBC, reason="malloc arenas are glibc's")
def test_one_arena_serves_every_thread_and_the_default_would_not() -> None:
    assert _arenas_in_use(_env()) == ("1", 1)
    limit, arenas = _arenas_in_use(_env(**{allocator.ARENAS_ENV: "0"}))  # glibc's own default
    assert limit == "None" and arenas > 1  # the probe can tell the difference


@pytest.mark.skipif(not GLIBC, reason="malloc arenas are glibc's")
def test_an_operators_malloc_arena_max_wins() -> None:
    assert _arenas_in_use(_env(MALLOC_ARENA_MAX="3"))[0] == "None"


def test_the_setting_is_read_and_checked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(allocator.ARENAS_ENV, raising=False)
    assert allocator.arenas_setting() == allocator.DEFAULT_ARENAS == 1
    monkeypatch.setenv(allocator.ARENAS_ENV, " 4 ")
    assert allocator.arenas_setting() == 4
    for bad in ("two", "-1", "1.5"):
        monkeypatch.setenv(allocator.ARENAS_ENV, bad)
        with pytest.raises(ValueError, match=allocator.ARENAS_ENV):
            allocator.arenas_setting()
    with pytest.raises(ValueError, match="at least 0"):
        allocator.configure_malloc(-2)
    assert allocator.configure_malloc(0) is None  # 0: nothing changed


def test_without_mallopt_nothing_is_changed(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("MALLOC_ARENA_MAX", raising=False)
    monkeypatch.setattr(allocator, "_libc", lambda: None)
    assert allocator.configure_malloc(1) is None


def test_the_cli_refuses_a_bad_setting_with_exit_2() -> None:
    proc = subprocess.run([sys.executable, "-m", "gradsep", "reconstruct", "missing.exr", "-o", "out.exr"],
                          env=_env(**{allocator.ARENAS_ENV: "many"}), cwd=REPO, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2
    assert allocator.ARENAS_ENV in proc.stderr and "Traceback" not in proc.stderr


# Three 30 MiB blocks at once, freed, three times over: glibc's adaptive thresholds hand the freed top of the heap
# back to the kernel (fresh pages the next time); the fixed ones keep it in the process, ready for the next frame.
_KEPT_PROBE = """
import sys
sys.path.insert(0, {repo!r})
import numpy as np
from gradsep.model.allocator import configure_malloc
configure_malloc()
def rss():
    return int(next(line for line in open("/proc/self/status") if line.startswith("VmRSS")).split()[1]) // 1024
base, kept = rss(), []
for _ in range(3):
    blocks = [np.ones(30 * 2**20, np.uint8) for _ in range(3)]
    del blocks
    kept.append(rss() - base)
print("kept", *kept)
"""


def _kept_mib(env: dict[str, str]) -> list[int]:
    out = subprocess.run([sys.executable, "-c", _KEPT_PROBE.format(repo=str(REPO))], env=env, check=True,
                         capture_output=True, text=True, timeout=120).stdout
    return [int(v) for v in out.split("kept")[1].split()]


@pytest.mark.skipif(not GLIBC, reason="malloc thresholds are glibc's")
def test_freed_frame_sized_blocks_stay_in_the_process() -> None:
    assert min(_kept_mib(_env())) >= 85  # all 90 MiB kept for the next frame
    assert max(_kept_mib(_env(**{allocator.ARENAS_ENV: "0"}))) < 85  # glibc's defaults return (some of) it
