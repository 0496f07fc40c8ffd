"""renderer/variant.py's libLLVM check: a suitable libLLVM is found in the library folders and named for Dr.Jit, a
user's DRJIT_LIBLLVM_PATH is kept, and without one `gradsep render` refuses in one line with exit status 2 before
any kernel is compiled (no real LLVM is needed for the refusal: the search is made to find nothing)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from gradsep.renderer import variant
from gradsep.renderer.variant import LLVM_ENV, MIN_LLVM, find_llvm, llvm_version, point_drjit_at_llvm

ROOT = Path(__file__).resolve().parents[2]


def _library(folder: Path, name: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_bytes(b"")
    return path


def test_llvm_version_reads_the_distributions_names(tmp_path: Path) -> None:
    assert llvm_version("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1") == 15
    assert llvm_version("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert llvm_version("/usr/lib/x86_64-linux-gnu/libLLVM-19.1.7.so") == 19
    assert llvm_version("/usr/lib/llvm-20/lib/libLLVM.so") == 20
    assert llvm_version("/usr/lib/x86_64-linux-gnu/libLLVMSPIRVLib.so.19") is None  # another library
    assert llvm_version("/usr/lib/libLLVM.so") is None  # nothing says which
    # a link says what its target says
    target = _library(tmp_path / "llvm-21" / "lib", "libLLVM.so.1")
    (tmp_path / "libLLVM.so").symlink_to(target)
    assert llvm_version(str(tmp_path / "libLLVM.so")) == 21


def test_find_llvm_takes_the_newest_suitable_library_or_none(tmp_path: Path) -> None:
    patterns = (str(tmp_path / "*" / "libLLVM*.so*"), str(tmp_path / "llvm-*" / "lib" / "libLLVM*.so*"))
    _library(tmp_path / "x86_64-linux-gnu", "libLLVM-14.so.1")
    _library(tmp_path / "x86_64-linux-gnu", "libLLVM-15.so")
    _library(tmp_path / "x86_64-linux-gnu", "libLLVMAArch64CodeGen.a")
    assert find_llvm(patterns) is None  # LLVM 14 and 15 abort while compiling Mitsuba 3.9's kernels
    suitable = _library(tmp_path / "x86_64-linux-gnu", f"libLLVM.so.{MIN_LLVM}.1")
    assert find_llvm(patterns) == str(suitable)
    newer = _library(tmp_path / f"llvm-{MIN_LLVM + 1}" / "lib", "libLLVM.so")
    assert find_llvm(patterns) == str(newer)


def test_point_drjit_at_llvm_names_the_library_and_keeps_the_users(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    suitable = _library(tmp_path, f"libLLVM-{MIN_LLVM}.so")
    patterns = (str(tmp_path / "libLLVM*.so*"),)
    monkeypatch.setattr(variant, "_llvm", {})
    env: dict[str, str] = {}
    assert point_drjit_at_llvm(env, patterns) == str(suitable) and env == {LLVM_ENV: str(suitable)}

    monkeypatch.setattr(variant, "_llvm", {})
    env = {LLVM_ENV: "/opt/my/libLLVM.so"}
    assert point_drjit_at_llvm(env, patterns) == "/opt/my/libLLVM.so" and env == {LLVM_ENV: "/opt/my/libLLVM.so"}

    monkeypatch.setattr(variant, "_llvm", {})
    env = {}
    assert point_drjit_at_llvm(env, (str(tmp_path / "none" / "*.so"),)) is None and env == {}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the refusal is Linux's (Dr.Jit's search elsewhere)")
def test_render_without_a_suitable_llvm_refuses_in_one_line(tmp_path: Path) -> None:
    """`gradsep render` on a machine whose search finds no libLLVM 19: one line naming the fix, exit status 2, no
    frame written, no LLVM abort (the CPU variant is asked for, so a GPU machine takes the same path)."""
    out = tmp_path / "frame.exr"
    script = (
        "import sys\n"
        "from gradsep.renderer import variant\n"
        "variant._llvm['path'] = None  # as if the search had found no suitable libLLVM\n"
        "from gradsep.cli import main\n"
        f"sys.exit(main(['render', 'procedural:1', '--spp', '1', '--width', '8', '--height', '8',\n"
        f"                '-o', {str(out)!r}]))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT), variant.VARIANT_ENV: variant.CPU_VARIANT}
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300,
                            cwd=ROOT)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("gradsep render: error:")
    assert "apt-get install libllvm19" in lines[0] and "make system-deps" in lines[0] and LLVM_ENV in lines[0]
    assert not out.exists()
