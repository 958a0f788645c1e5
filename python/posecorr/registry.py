"""The tables posecorr looks names up in (activations, methods, ...): one lookup and one refusal."""
from __future__ import annotations

from typing import Any, Sequence

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

    def lookup(self, name: str, among: Sequence[str] | None = None, hint: str = "") -> Any:
        """The entry `name`; a refusal names `among` (default: every entry), the entries the
        asking option takes, as the likely and the expected names, then `hint`: what else the
        asking option's user may have meant."""
        try:
            return self[name]
        except KeyError:
            known = list(self) if among is None else list(among)
            raise ValueError(f"unknown {self.kind} {name!r}{did_you_mean(str(name), known)}; "
                             f"expected one of {', '.join(known)}{'; ' + hint if hint else ''}") from None
