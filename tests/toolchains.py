"""The cross toolchains some test modules need (.ci/run installs them): without them a module
is skipped, unless POSECORR_REQUIRE_EMBEDDED=1 (set by .ci/run), where a missing tool is a
failure rather than a quiet skip."""
from __future__ import annotations

import os
import shutil

import pytest


def require(what: str, tools: tuple[str, ...], packages: str) -> None:
    """Skip the calling module (or fail, on CI) unless every one of `tools` is on PATH."""
    missing = [tool for tool in tools if shutil.which(tool) is None]
    if not missing:
        return
    reason = f"{what} not installed: {', '.join(missing)} (apt-get install {packages})"
    if os.environ.get("POSECORR_REQUIRE_EMBEDDED") == "1":
        raise RuntimeError(reason)
    pytest.skip(reason, allow_module_level=True)
