"""Output shared by the benchmark scripts (run as ``python bench/NAME.py``, so ``bench/`` is on
the import path)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def emit_json(data: Any, path: str | Path | None = None) -> None:
    """Print ``data`` as indented JSON and, when ``path`` is given, also write it there."""
    text = json.dumps(data, indent=1)
    print(text)
    if path:
        Path(path).write_text(text + "\n")
