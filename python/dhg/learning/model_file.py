"""What a model file (``model.ts``, :mod:`dhg.learning.torchscript`) says of itself, read without
torch: its metadata (the archive's extra file ``dhg.json``) and what identifies it. The engine
alone (``dhg-serve --role sim``) reads its corridor profile from here, and a server's ``about``
reply names its model from here, so neither loads torch for it."""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from pathlib import Path
from typing import Any

from dhg.core.errors import DhgError
from dhg.core.features import FEATURE_NAMES

__all__ = ["META_NAME", "MODEL_FORMAT", "MODEL_VERSION", "ModelFileError", "model_identity", "read_model_meta"]

MODEL_FORMAT = "dhg-model"
MODEL_VERSION = 1
META_NAME = "dhg.json"


class ModelFileError(DhgError, ValueError):
    """A model file that is missing, corrupt, or not a DHG model."""


def read_model_meta(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The metadata of an exported model, read with :mod:`zipfile` only."""
    p = Path(path)
    try:
        with zipfile.ZipFile(p) as z:
            name = next((n for n in z.namelist() if n.endswith(f"/extra/{META_NAME}")), None)
            if name is None:
                raise ModelFileError(f"{p}: no {META_NAME} inside: not a DHG model")
            meta = json.loads(z.read(name))
    except FileNotFoundError:
        raise ModelFileError(f"{p}: no such model file") from None
    except (zipfile.BadZipFile, OSError, json.JSONDecodeError, KeyError) as exc:
        raise ModelFileError(f"{p}: unreadable model file ({exc})") from None
    if meta.get("format") != MODEL_FORMAT or meta.get("version") != MODEL_VERSION:
        raise ModelFileError(
            f"{p}: format {meta.get('format')} v{meta.get('version')}, expected {MODEL_FORMAT} v{MODEL_VERSION}"
        )
    if meta.get("input", {}).get("features") != list(FEATURE_NAMES):
        raise ModelFileError(
            f"{p}: trained on features {meta.get('input', {}).get('features')}, not {list(FEATURE_NAMES)}"
        )
    return meta


def model_identity(path: str | os.PathLike[str], meta: dict[str, Any]) -> dict[str, Any]:
    """What identifies the model in ``path`` with metadata ``meta``: its file's name (not its
    folders) and SHA-256 (None if the file cannot be read now), its ``preset``, ``window`` and
    ``horizon_records`` (records), the ``records_sha256`` of the data it was trained on (as in
    that dataset's card) and the ``dhg_version`` that exported it."""
    p = Path(path)
    h = hashlib.sha256()
    digest: str | None = None
    try:
        with p.open("rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        digest = h.hexdigest()
    except OSError:  # moved or deleted since it was loaded: the rest still says what it was
        pass
    data = meta.get("data")
    return {
        "file": p.name,
        "sha256": digest,
        "preset": meta.get("preset"),
        "window": meta.get("window"),
        "horizon_records": int(meta.get("horizon_records", 1)),
        "records_sha256": data.get("records_sha256") if isinstance(data, dict) else None,
        "dhg_version": meta.get("dhg_version"),
    }
