"""Atomic artifact writing: write to a temporary file beside the target, then rename.

A run that fails or is interrupted never leaves a half-written file where a good one was. Every
write and read goes through ``pipeline.io.files``: no link followed inside an output folder, the
folder written through its descriptor, reads bounded (``ARTIFACT_MAX_BYTES`` per artifact file).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import logging
import os
import secrets
import shutil
import zipfile
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from pipeline.io.files import (
    ARTIFACT_MAX_BYTES,
    FileRefused,
    PathRefused,
    open_folder,
    open_regular,
    printable,
    read_bytes,
    remove_files,
)

TEMPORARY = ".tmp"
log = logging.getLogger(__name__)


def _atomic(
    path: Path, write: Callable[[BinaryIO], object], suffix: str = "", cache: bool = False
) -> None:
    """Call ``write(stream)`` on a new temporary file beside ``path`` (``.NAME.XXXX.tmp`` +
    ``suffix``) and rename it to ``path``; on any failure delete exactly that temporary.

    The folder is opened once (``pipeline.io.files.open_folder``: inside a held output folder,
    no link followed) and the temporary is created (``O_EXCL | O_NOFOLLOW``), renamed and deleted
    through its descriptor, so a folder swapped for a link meanwhile cannot redirect the write.
    A folder where ``path`` belongs is replaced when ``cache`` (a cache file's place: the
    pipeline's own), else refused in one line (``PathRefused``)."""
    path = Path(path)
    folder = open_folder(path.parent, create=True)
    try:
        temporary, handle = _temporary(folder, path.name, suffix)
        try:
            with os.fdopen(handle, "wb") as stream:
                write(stream)
            _replace(folder, temporary, path, cache)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(temporary, dir_fd=folder)
            raise
    finally:
        os.close(folder)


def _temporary(folder: int, name: str, suffix: str) -> tuple[str, int]:
    """A new file ``.NAME.XXXXXXXXXXXX.tmp`` + ``suffix`` in ``folder``: its name and a
    descriptor open for writing (mode 0666 less the umask, as for any file the user makes)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    while True:
        temporary = f".{name}.{secrets.token_hex(6)}{TEMPORARY}{suffix}"
        try:
            return temporary, os.open(temporary, flags, 0o666, dir_fd=folder)
        except FileExistsError:
            continue  # 2^-48 per try


def _replace(folder: int, temporary: str, path: Path, cache: bool) -> None:
    try:
        os.replace(temporary, path.name, src_dir_fd=folder, dst_dir_fd=folder)
    except IsADirectoryError:
        if not cache:
            raise PathRefused(
                "is a folder where the run writes a file",
                file=printable(str(path)),
                expected="a file: remove or rename that folder",
            ) from None
        log.warning(f"{printable(str(path))}: a folder where a cache file belongs; replaced")
        shutil.rmtree(path.name, dir_fd=folder)
        os.replace(temporary, path.name, src_dir_fd=folder, dst_dir_fd=folder)


def remove_temporaries(folder: Path) -> list[Path]:
    """Delete the temporaries that killed writers left in ``folder`` (call it only while holding
    the folder's lock, when no writer can be active); returns what was deleted."""
    removed = remove_files(folder, lambda name: name.startswith(".") and TEMPORARY in name)
    return [Path(folder) / name for name in removed]


def atomic_write_text(path: Path, text: str, cache: bool = False) -> None:
    """Write ``text`` to ``path`` atomically, as UTF-8; a byte of a file name that is not UTF-8
    (a lone surrogate, ``os.fsdecode``) is written back as that byte (``os.fsencode``)."""
    try:
        data = text.encode("utf-8", "surrogateescape")
    except UnicodeEncodeError:  # a lone surrogate that is not an escaped byte: shown, as text
        data = printable(text).encode("utf-8")
    _atomic(path, lambda stream: stream.write(data), cache=cache)


def atomic_write_json(path: Path, data: Any) -> None:
    """Write ``data`` as indented JSON to ``path`` atomically."""
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=False) + "\n")


def atomic_save(
    path: Path, save: Callable[[BinaryIO], object], suffix: str = "", cache: bool = False
) -> None:
    """Call ``save(stream)`` (e.g. ``fig.savefig(stream, format="png")``) on a binary file
    that is then renamed to ``path`` (see ``_atomic``); the temporary's name ends in ``suffix``.
    """
    _atomic(path, save, suffix, cache)


def file_hash(path: Path, limit: int = ARTIFACT_MAX_BYTES) -> str:
    """SHA-256 of a regular file's bytes (at most ``limit``: ``FileRefused`` beyond), hex."""
    fd = open_regular(path)
    with os.fdopen(fd, "rb") as stream:
        size = os.fstat(fd).st_size
        if size > limit:
            raise FileRefused(path, f"is {size:,} bytes; expected at most {limit:,}")
        return hashlib.file_digest(stream, "sha256").hexdigest()


# --- Stage results as artifacts: JSON for the structure, .npz for the larger arrays. ---------
#
# Nothing read from disk chooses code to run: a dataclass node names a type, and decoding looks
# that name up in the caller's registry (``pipeline.runtime.registry``) and calls that class with
# exactly its declared fields; any other name or field refuses the artifact. Each artifact stores
# a SHA-256 over its JSON tree, its key and every array, so an edited or damaged file is refused.

SMALL_ARRAY = 64
FORMAT = "stage-artifact/2"


class ArtifactError(ValueError):
    """A stored artifact is corrupt, was edited, or names a type outside the registry."""

    def __init__(self, reason: str, file: Path | None = None) -> None:
        self.reason, self.file = reason, file
        super().__init__(reason if file is None else f"{file}: {reason}")


def type_name(cls: type) -> str:
    """The name a dataclass is stored under: ``module:qualname``."""
    return f"{cls.__module__}:{cls.__qualname__}"


def _encode(value: Any, arrays: dict[str, np.ndarray], exact: bool = False) -> Any:
    """``value`` as a JSON tree, its larger arrays moved to ``arrays`` (named in the tree).

    Every node is tagged (``__dataclass__`` with its type's name, ``__tuple__``, ``__dict__`` as
    ``[key, value]`` pairs in order, ``__path__``, ``__array__`` with dtype and shape, ``__npz__``),
    so two values of different types or structure never give one tree. With ``exact`` (the
    cache keys, ``inputs_key``) a NumPy scalar keeps its dtype (a 0-d array), a ``str``, ``int``
    or ``float`` subclass (an enum) and an array of another kind than bool, integer or float
    are refused; the store (``save_result``) keeps its format, NumPy scalars as Python numbers.
    Anything else raises ``TypeError`` naming its type: nothing is encoded by ``str()``.
    """
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        fields = {
            f.name: _encode(getattr(value, f.name), arrays, exact)
            for f in dataclasses.fields(value)
        }
        return {"__dataclass__": type_name(type(value)), "fields": fields}
    if isinstance(value, np.generic) and exact:
        value = np.asarray(value)  # its dtype kept: np.float32(1) is not 1.0
    if isinstance(value, np.ndarray):
        if value.dtype == object:
            raise TypeError("cannot encode an object array (in an artifact or a cache key)")
        if exact and value.dtype.kind not in "biuf":
            raise TypeError(f"cannot encode an array of dtype {value.dtype} in a cache key")
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
        return {"__tuple__": [_encode(v, arrays, exact) for v in value]}
    if isinstance(value, list):
        return [_encode(v, arrays, exact) for v in value]
    if isinstance(value, Mapping):
        pairs = [[_encode(k, arrays, exact), _encode(v, arrays, exact)] for k, v in value.items()]
        return {"__dict__": pairs}
    if value is None or type(value) in (bool, int, float, str):
        return value
    if isinstance(value, (bool, int, float, str)) and not exact:
        return value
    raise TypeError(f"cannot encode a {type(value).__qualname__} (in an artifact or a cache key)")


def _decode(value: Any, arrays: Mapping[str, np.ndarray], registry: Mapping[str, type]) -> Any:
    if isinstance(value, list):
        return [_decode(v, arrays, registry) for v in value]
    if not isinstance(value, dict):
        return value
    if "__dataclass__" in value:
        name = value["__dataclass__"]
        cls = registry.get(name) if isinstance(name, str) else None
        if cls is None:
            raise ArtifactError(f"names type {name!r}, which is not a registered result type")
        stored = value.get("fields")
        declared = {f.name for f in dataclasses.fields(cls) if f.init}
        if not isinstance(stored, dict) or set(stored) != declared:
            found = sorted(stored) if isinstance(stored, dict) else stored
            raise ArtifactError(
                f"fields of {name} do not match its declaration; found {found}, "
                f"expected {sorted(declared)}"
            )
        return cls(**{k: _decode(v, arrays, registry) for k, v in stored.items()})
    if "__array__" in value:
        return np.array(value["__array__"], dtype=np.dtype(value["dtype"])).reshape(value["shape"])
    if "__npz__" in value:
        return arrays[value["__npz__"]]
    if "__path__" in value:
        return Path(value["__path__"])
    if "__tuple__" in value:
        return tuple(_decode(v, arrays, registry) for v in value["__tuple__"])
    if "__dict__" in value:
        return {
            _decode(k, arrays, registry): _decode(v, arrays, registry) for k, v in value["__dict__"]
        }
    raise ArtifactError(f"unknown artifact node with keys {sorted(value)}")


def content_hash(key: str, tree: Any, arrays: Mapping[str, np.ndarray]) -> str:
    """SHA-256 over an artifact's key, JSON tree and arrays (name, dtype, shape, bytes)."""
    digest = hashlib.sha256(json.dumps([key, tree], sort_keys=True).encode())
    for name in sorted(arrays):
        array = np.ascontiguousarray(arrays[name])
        digest.update(f"\x00{name}:{array.dtype.str}:{array.shape}\x00".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def save_result(stem: Path, key: str, result: Any) -> str:
    """Store a stage result as ``stem.json`` (+ ``stem.npz``), tagged with its inputs' ``key``;
    returns the content hash stored with it.

    The arrays are written first, the JSON (which holds the key and the content hash) last, each
    atomically: a run interrupted between the two leaves a pair whose hash does not match.
    """
    arrays: dict[str, np.ndarray] = {}
    tree = _encode(result, arrays)
    sha256 = content_hash(key, tree, arrays)
    npz = stem.with_suffix(".npz")
    atomic_save(
        npz,
        lambda stream: np.savez_compressed(
            stream, allow_pickle=True, __key__=np.array(key), **arrays
        ),
        suffix=".npz",
        cache=True,
    )
    document = {"format": FORMAT, "key": key, "sha256": sha256, "result": tree}
    text = json.dumps(document, indent=1) + "\n"
    atomic_write_text(stem.with_suffix(".json"), text, cache=True)
    return sha256


@dataclasses.dataclass(frozen=True, kw_only=True)
class Stored:
    """A stored stage result as read back: its input ``key``, content ``sha256`` and value."""

    key: str
    sha256: str
    result: Any


# everything a damaged .json/.npz can raise on reading (truncated, bit-flipped, empty, edited)
_DAMAGE = (
    OSError,
    EOFError,
    ValueError,
    KeyError,
    TypeError,
    AttributeError,
    RecursionError,
    zipfile.BadZipFile,
    zlib.error,
    MemoryError,  # an array header that declares more than memory holds
)


def read_stored(stem: Path, registry: Mapping[str, type]) -> Stored | None:
    """The artifact ``stem.json`` + ``stem.npz``; ``None`` when either file is missing.

    Raises ``ArtifactError`` (one line, naming the file) when it is unreadable, not a regular
    file, larger than ``ARTIFACT_MAX_BYTES`` (its arrays expanded: 4 times that), corrupt, does
    not match its content hash, or names a type or field outside ``registry``.
    """
    json_path, npz_path = stem.with_suffix(".json"), stem.with_suffix(".npz")
    try:
        raw_json = read_bytes(json_path, ARTIFACT_MAX_BYTES)
        raw_npz = read_bytes(npz_path, ARTIFACT_MAX_BYTES)
    except FileNotFoundError:
        return None
    except FileRefused as error:
        raise ArtifactError(f"{error.path.name} {error.reason}", json_path) from None
    try:
        document = json.loads(raw_json)
        if not isinstance(document, dict) or document.get("format") != FORMAT:
            raise ArtifactError("not a stage artifact of this version")
        key, sha256, tree = document["key"], document["sha256"], document["result"]
        with np.load(io.BytesIO(raw_npz), allow_pickle=False) as stored:
            expanded = sum(info.file_size for info in stored.zip.infolist())
            if expanded > 4 * ARTIFACT_MAX_BYTES:
                raise ArtifactError(f"{npz_path.name} expands to {expanded:,} bytes")
            arrays = {name: stored[name] for name in stored.files}
        if str(arrays.pop("__key__")) != key:
            raise ArtifactError(f"{npz_path.name} belongs to another run than {json_path.name}")
        if content_hash(key, tree, arrays) != sha256:
            raise ArtifactError("content does not match its stored sha256 (edited or damaged)")
        return Stored(key=str(key), sha256=str(sha256), result=_decode(tree, arrays, registry))
    except ArtifactError as error:
        raise ArtifactError(error.reason, json_path) from None
    except _DAMAGE as error:
        reason = f"unreadable ({type(error).__name__}: {error})"
        raise ArtifactError(reason, json_path) from None


def inputs_key(*parts: Any) -> str:
    """A hash of a stage's inputs: SHA-256 (first 16 hex digits) of ``parts`` as the artifact
    store encodes them (``_encode`` with ``exact``), over ``content_hash``.

    The encoding is injective: every node is tagged with its type (a dataclass by its name and
    fields; tuple, list, mapping and path apart; ``1``, ``1.0`` and ``True`` apart; floats by
    their shortest exact ``repr``), every array carries its dtype and shape (a ``(2, 3)``, a
    ``(3, 2)`` and an int ``(6, 1)`` array of the same bytes differ) and is hashed whole, JSON is
    self-delimiting and the bytes of each array follow a header fixing their length, so no two
    values give one byte stream (``("ab", "c")`` is not ``("a", "bc")``). A mapping is encoded in
    its order: the stages iterate mappings (the Unsafe sets, the operating region), and sums in
    another order can differ in the last bits. A value it cannot encode exactly (a set, an enum,
    a sympy expression, an object array) raises ``TypeError`` naming its type.
    """
    arrays: dict[str, np.ndarray] = {}
    tree = _encode(parts, arrays, exact=True)
    return content_hash("inputs", tree, arrays)[:16]
