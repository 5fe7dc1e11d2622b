"""Atomic artifact writing: write to a temporary file beside the target, then rename.

A run that fails or is interrupted never leaves a half-written file where a good one was.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
import os
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np


def _atomic(path: Path, write: Callable[[Path], None]) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(handle)
    try:
        write(Path(temporary))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temporary, 0o666 & ~umask)  # mkstemp creates 0600; a report is for reading
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    _atomic(path, lambda temporary: temporary.write_text(text))


def atomic_write_json(path: Path, data: Any) -> None:
    """Write ``data`` as indented JSON to ``path`` atomically."""
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=False) + "\n")


def atomic_save(path: Path, save: Callable[[Path], None], suffix: str = "") -> None:
    """Call ``save(temporary_path)`` (e.g. ``fig.savefig``) and rename the result to ``path``.

    ``suffix`` is appended to the temporary name for writers that infer the format from it.
    """

    def write(temporary: Path) -> None:
        with_suffix = temporary.with_name(temporary.name + suffix)
        save(with_suffix)
        if with_suffix != temporary:
            os.replace(with_suffix, temporary)

    _atomic(path, write)


def file_hash(path: Path) -> str:
    """SHA-256 of a file's bytes, hex."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# --- Stage results as artifacts: JSON for the structure, .npz for the larger arrays. ---------

SMALL_ARRAY = 64


def _encode(value: Any, arrays: dict[str, np.ndarray]) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        cls = type(value)
        fields = {
            f.name: _encode(getattr(value, f.name), arrays) for f in dataclasses.fields(value)
        }
        return {"__dataclass__": f"{cls.__module__}:{cls.__qualname__}", "fields": fields}
    if isinstance(value, np.ndarray):
        if value.dtype == object:
            raise TypeError("object arrays cannot be stored as artifacts")
        if value.size <= SMALL_ARRAY:
            return {"__array__": value.tolist(), "dtype": value.dtype.str, "shape": value.shape}
        key = f"a{len(arrays)}"
        arrays[key] = value
        return {"__npz__": key}
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return {"__path__": str(value)}
    if isinstance(value, tuple):
        return {"__tuple__": [_encode(v, arrays) for v in value]}
    if isinstance(value, list):
        return [_encode(v, arrays) for v in value]
    if isinstance(value, Mapping):
        return {"__dict__": [[_encode(k, arrays), _encode(v, arrays)] for k, v in value.items()]}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"cannot store a {type(value).__name__} in an artifact")


def _decode(value: Any, arrays: Mapping[str, np.ndarray]) -> Any:
    if isinstance(value, list):
        return [_decode(v, arrays) for v in value]
    if not isinstance(value, dict):
        return value
    if "__dataclass__" in value:
        module, name = value["__dataclass__"].split(":")
        cls: Any = importlib.import_module(module)
        for part in name.split("."):
            cls = getattr(cls, part)
        return cls(**{k: _decode(v, arrays) for k, v in value["fields"].items()})
    if "__array__" in value:
        return np.array(value["__array__"], dtype=np.dtype(value["dtype"])).reshape(value["shape"])
    if "__npz__" in value:
        return arrays[value["__npz__"]]
    if "__path__" in value:
        return Path(value["__path__"])
    if "__tuple__" in value:
        return tuple(_decode(v, arrays) for v in value["__tuple__"])
    if "__dict__" in value:
        return {_decode(k, arrays): _decode(v, arrays) for k, v in value["__dict__"]}
    raise ValueError(f"unknown artifact node with keys {sorted(value)}")


def save_result(stem: Path, key: str, result: Any) -> None:
    """Store a stage result as ``stem.json`` (+ ``stem.npz``), tagged with its inputs' ``key``.

    The arrays are written first, the JSON (which names the key) last, each atomically: a run
    interrupted between the two leaves a JSON whose key does not match the arrays, i.e. a miss.
    """
    arrays: dict[str, np.ndarray] = {}
    tree = _encode(result, arrays)
    npz = stem.with_suffix(".npz")
    atomic_save(
        npz, lambda p: np.savez_compressed(p, __key__=np.array(key), **arrays), suffix=".npz"
    )
    atomic_write_text(
        stem.with_suffix(".json"), json.dumps({"key": key, "result": tree}, indent=1) + "\n"
    )


def read_result(stem: Path) -> Any:
    """The stored result of ``stem`` whatever its key (for reports); raises if missing/broken."""
    document = json.loads(stem.with_suffix(".json").read_text())
    result = load_result(stem, document["key"])
    if result is None:
        raise FileNotFoundError(f"{stem}: artifact missing or incomplete; re-run synthesize")
    return result


def load_result(stem: Path, key: str) -> Any | None:
    """The stored result of ``stem`` if both files exist and carry ``key``; else ``None``."""
    json_path, npz_path = stem.with_suffix(".json"), stem.with_suffix(".npz")
    if not (json_path.is_file() and npz_path.is_file()):
        return None
    try:
        document = json.loads(json_path.read_text())
        with np.load(npz_path, allow_pickle=False) as stored:
            if document.get("key") != key or str(stored["__key__"]) != key:
                return None
            arrays = {name: stored[name] for name in stored.files}
        return _decode(document["result"], arrays)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def inputs_key(*parts: Any) -> str:
    """A content hash of a stage's inputs (strings, numbers, arrays, JSON-able structures)."""
    digest = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            digest.update(np.ascontiguousarray(part, dtype=np.float64).tobytes())
        else:
            digest.update(json.dumps(part, sort_keys=True, default=str).encode())
        digest.update(b"\x00")
    return digest.hexdigest()[:16]
