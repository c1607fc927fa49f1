"""Device drivers, the recorder and the recording format (the on-disk contract).

Installed as :mod:`mocaprig.acquire`. Imports flow one way: ``process -> calib -> acquire``.
"""

from __future__ import annotations

__all__: list[str] = []
