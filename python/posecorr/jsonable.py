"""numpy values in JSON: ``json.dumps(obj, default=json_default)`` (the CLI's --json, sidecars)."""
from __future__ import annotations

from typing import Any


def json_default(value: Any) -> Any:
    """A numpy scalar or array as the Python number or list it holds; TypeError otherwise."""
    import numpy as np  # only ever called with numpy loaded: nothing else reaches it

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
