"""Builds the C runtime with CMake and places libposecorr next to the Python package.

The shared library is not a CPython extension; it is loaded with ctypes by
`posecorr.runtime`. It is declared as an extension only so that setuptools builds it
in place for editable installs and into the wheel otherwise.
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
    def build_extension(self, ext: Extension) -> None:
        if not isinstance(ext, CMakeLibrary):
            return super().build_extension(ext)
        build_dir = Path(self.build_temp).resolve() / "runtime_c"
        build_dir.mkdir(parents=True, exist_ok=True)
        cmake = shutil.which("cmake") or "cmake"
        subprocess.check_call([cmake, "-S", str(ext.source_dir), "-B", str(build_dir),
                               "-DCMAKE_BUILD_TYPE=Release", "-DPC_BUILD_TESTS=OFF",
                               f"-DPython3_EXECUTABLE={sys.executable}"])
        subprocess.check_call([cmake, "--build", str(build_dir), "--parallel", "2"])
        # ctypes needs a plain file name it can find: copy the library and the tools
        # into posecorr/_native beside the package, whatever the extension suffix.
        target = Path(self.get_ext_fullpath(ext.name)).parent
        target.mkdir(parents=True, exist_ok=True)
        for name in ("libposecorr.so", "libposecorr.dylib", "posecorr-run", "posecorr-bench"):
            built = build_dir / name
            if built.exists():
                shutil.copy2(built, target / name)
        # setuptools expects the extension's own file; point it at the library.
        shutil.copy2(build_dir / "libposecorr.so", self.get_ext_fullpath(ext.name))


setup(
    ext_modules=[CMakeLibrary("posecorr._native.libposecorr_ext", ROOT / "runtime_c")],
    cmdclass={"build_ext": BuildWithCMake},
)
