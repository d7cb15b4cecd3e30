"""A value with its standard uncertainty and unit: how results report a measured quantity."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Quantity:
    """``value`` with standard uncertainty ``u`` (k = 1), both in ``unit``."""

    value: float
    u: float
    unit: str = ""

    @property
    def relative_u(self) -> float:
        """u / |value| (dimensionless)."""
        return abs(self.u / self.value)

    def to_dict(self) -> dict:
        """``{"value", "u", "unit"}``, JSON-ready."""
        return {"value": float(self.value), "u": float(self.u), "unit": self.unit}
