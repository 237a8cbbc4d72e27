"""The registry of scenario kinds: a kind's name (as recorded in the files) to its hooks."""

from __future__ import annotations

from functools import cache

from fusionlog.errors import FusionlogError

from .hooks import Kind


@cache
def kind_of(name: str) -> Kind:
    """The hooks of the kind `name` ("state" or "identity"); each is imported on first use, so
    a command pays only for the kind it runs."""
    if name == "state":
        from .state_kind import StateKind

        return StateKind()
    if name == "identity":
        from .identity_kind import IdentityKind

        return IdentityKind()
    raise FusionlogError(f"unknown kind of scenario {name!r} (known: state, identity)")
