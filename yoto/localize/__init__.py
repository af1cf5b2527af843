"""Contact localization: where on the object model is a tactile contact? One module per method."""

from __future__ import annotations

from yoto.errors import require_torch
from yoto.localize.base import ContactLocalizer, OracleLocalizer

METHODS = ("oracle", "icp", "match", "yoto")


def make_localizer(method: str, checkpoint: str | None = None) -> ContactLocalizer:
    """The localizer for a method name; heavy dependencies are imported only for the method asked for."""
    if method == "oracle":
        return OracleLocalizer()
    if method == "icp":
        from yoto.localize.icp import IcpLocalizer

        return IcpLocalizer()
    if method == "match":
        from yoto.localize.scaled_match import ScaledMatchLocalizer

        return ScaledMatchLocalizer()  # the matched filter, with finer cells for contacts too small for its default
    if method == "yoto":
        require_torch("the YOTO network localizer")
        from yoto.localize.network import load_localizer

        return load_localizer(checkpoint)
    raise ValueError(f"unknown localization method {method!r} (use one of {', '.join(METHODS)})")


__all__ = ["METHODS", "ContactLocalizer", "OracleLocalizer", "make_localizer"]
