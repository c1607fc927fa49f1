"""Body model, capture methods (DeMoCap, EventCap), metrics and exporters.

Imports flow one way: ``process -> calib -> acquire``. Subpackages: :mod:`mocaprig.process.body`.
"""

from __future__ import annotations

__all__: list[str] = []
