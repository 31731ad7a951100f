"""Reading the project's JSON and YAML files with clear errors (one place for all loaders)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["read_document"]


def read_document(path: str | Path, what: str, *, fmt: str | None = None) -> Any:
    """The parsed content of ``path`` (JSON for ``.json`` or ``fmt="json"``, else YAML).

    FileNotFoundError names ``what`` is missing; ValueError says the file is not valid JSON or
    YAML. The content is returned as parsed: callers check its shape.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{what} {p} not found")
    text = p.read_text()
    if (fmt or ("json" if p.suffix == ".json" else "yaml")) == "json":
        try:
            return json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{p}: not valid JSON ({exc})") from None
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"{p}: not valid YAML ({exc})") from None
