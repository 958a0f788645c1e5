"""The tables posecorr looks names up in (activations, methods, ...): one lookup and one refusal."""
from __future__ import annotations

from typing import Any

from .textui import did_you_mean


class Registry(dict):
    """name -> entry. `add` refuses a name twice; `lookup` names the known entries when it fails."""

    def __init__(self, kind: str) -> None:
        super().__init__()
        self.kind = kind

    def add(self, name: str, entry: Any) -> Any:
        if name in self:
            raise ValueError(f"{self.kind} {name!r} is already registered")
        self[name] = entry
        return entry

    def lookup(self, name: str) -> Any:
        try:
            return self[name]
        except KeyError:
            raise ValueError(f"unknown {self.kind} {name!r}{did_you_mean(str(name), list(self))}; "
                             f"expected one of {', '.join(self)}") from None
