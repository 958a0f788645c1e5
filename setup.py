"""Builds the C runtime with CMake and places libposecorr next to the Python package.

The shared library is not a CPython extension; it is loaded with ctypes by
`posecorr.controller.runtime`. It is declared as an extension only so that setuptools builds it
in place for editable installs (python/posecorr/_native/) and into the wheel otherwise.
`posecorr.controller._call1` is a real (optional) extension: the shim's single-pose fast path.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

ROOT = Path(__file__).resolve().parent


class CMakeLibrary(Extension):
    def __init__(self, name: str, source_dir: Path) -> None:
        super().__init__(name, sources=[])
        self.source_dir = source_dir


class BuildWithCMake(build_ext):
    """Runs CMake for the C runtime; library and tools land in posecorr/_native/."""

    TOOLS = ("posecorr-run", "posecorr-bench", "posecorr-plan")
    # formulas.h: copied into the C that `posecorr compile` writes (the runtime's element
    # formulas); posecorr.h: the header of the library beside it, for a program linked to it.
    HEADERS = ("formulas.h", "posecorr.h")

    def get_ext_filename(self, fullname: str) -> str:
        ext = self.ext_map.get(fullname)
        if isinstance(ext, CMakeLibrary):
            # A plain file name: ctypes loads it, CPython never imports it.
            return os.path.join(*fullname.split(".")) + ".so"
        return super().get_ext_filename(fullname)

    def build_extension(self, ext: Extension) -> None:
        if not isinstance(ext, CMakeLibrary):
            return super().build_extension(ext)
        build_dir = Path(self.build_temp).resolve() / "runtime_c"
        build_dir.mkdir(parents=True, exist_ok=True)
        cmake = shutil.which("cmake") or "cmake"
        subprocess.check_call([cmake, "-S", str(ext.source_dir), "-B", str(build_dir),
                               "-DCMAKE_BUILD_TYPE=Release", "-DPC_BUILD_TESTS=OFF",
                               # one copy under its plain name: its SONAME must be that name
                               "-DPC_VERSIONED_SONAME=OFF",
                               f"-DPython3_EXECUTABLE={sys.executable}"])
        subprocess.check_call([cmake, "--build", str(build_dir), "--parallel", "2"])
        target = Path(self.get_ext_fullpath(ext.name))
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(build_dir / "libposecorr.so", target)
        for tool in self.TOOLS:
            shutil.copy2(build_dir / tool, target.parent / tool)
        for header in self.HEADERS:
            shutil.copy2(Path(ext.source_dir) / header, target.parent / header)

    def copy_extensions_to_source(self) -> None:
        # Editable installs: the tools travel with the library into the source tree.
        build_py = self.get_finalized_command("build_py")
        for ext in self.extensions:
            inplace_file, regular_file = self._get_inplace_equivalent(build_py, ext)
            Path(inplace_file).parent.mkdir(parents=True, exist_ok=True)
            if isinstance(ext, CMakeLibrary):
                for tool in self.TOOLS + self.HEADERS:
                    self.copy_file(str(Path(regular_file).parent / tool), str(Path(inplace_file).parent / tool))
        super().copy_extensions_to_source()


setup(
    ext_modules=[CMakeLibrary("posecorr._native.libposecorr", ROOT / "runtime_c"),
                 # The shim's single-pose fast path; optional: without the interpreter's
                 # headers the shim calls through ctypes alone.
                 Extension("posecorr.controller._call1",
                           sources=["python/posecorr/controller/call1.c"], optional=True)],
    cmdclass={"build_ext": BuildWithCMake},
)
