"""Strict JSON for tests: what a strict parser (another language's, a JSON schema validator) accepts."""

from __future__ import annotations

import json
from typing import Any


def strict_loads(text: str) -> Any:
    """``json.loads`` that refuses ``NaN``, ``Infinity`` and ``-Infinity`` (Python's json accepts them)."""

    def refuse(token: str) -> Any:
        raise ValueError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=refuse)
