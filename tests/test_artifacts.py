"""Atomic writes and stage-result artifacts."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import pytest

from pipeline.io.artifacts import (
    ArtifactError,
    atomic_save,
    atomic_write_text,
    inputs_key,
    read_stored,
    save_result,
    type_name,
)


@dataclass(frozen=True)
class Inner:
    values: np.ndarray
    label: str


@dataclass(frozen=True)
class Outer:
    items: tuple[Inner, ...]
    table: dict[str, float]
    small: np.ndarray
    flag: bool


REGISTRY = {type_name(Inner): Inner, type_name(Outer): Outer}


def load_result(stem, key):
    """The stored result if its key is ``key``, else None (a miss)."""
    stored = read_stored(stem, REGISTRY)
    return stored.result if stored is not None and stored.key == key else None


def _result() -> Outer:
    big = np.random.default_rng(0).normal(size=(300, 6))
    return Outer((Inner(big, "a"), Inner(big[:2], "b")), {"x": 1.5, "y": np.inf}, np.eye(2), True)


def test_round_trip_keeps_types_and_values(tmp_path):
    original = _result()
    save_result(tmp_path / "stage", "key1", original)
    loaded = load_result(tmp_path / "stage", "key1")
    assert isinstance(loaded, Outer) and isinstance(loaded.items, tuple)
    np.testing.assert_array_equal(loaded.items[0].values, original.items[0].values)
    np.testing.assert_array_equal(loaded.small, original.small)
    assert loaded.table == original.table and loaded.flag is True


def test_another_key_is_a_miss(tmp_path):
    save_result(tmp_path / "stage", "key1", _result())
    assert load_result(tmp_path / "stage", "key2") is None
    assert load_result(tmp_path / "missing", "key1") is None


def test_half_written_pair_is_refused(tmp_path):
    save_result(tmp_path / "stage", "old", _result())
    # an interrupted save of a new result: the arrays were replaced, the JSON was not
    np.savez(tmp_path / "stage.npz", __key__=np.array("new"))
    with pytest.raises(ArtifactError, match="belongs to another run"):
        read_stored(tmp_path / "stage", REGISTRY)


def test_unregistered_type_is_refused_and_nothing_else_is_called(tmp_path):
    save_result(tmp_path / "stage", "k", _result())
    with pytest.raises(ArtifactError, match="not a registered result type"):
        read_stored(tmp_path / "stage", {type_name(Outer): Outer})  # Inner not registered


def test_failed_write_keeps_the_previous_file(tmp_path):
    target = tmp_path / "report.txt"
    atomic_write_text(target, "good")

    def broken(stream):
        stream.write(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_save(target, broken)
    assert target.read_text() == "good"
    assert [p.name for p in tmp_path.iterdir()] == ["report.txt"]


@pytest.mark.parametrize("suffix", [".npz", ".pdf", ""])
def test_failed_save_deletes_exactly_the_temporary_it_made(tmp_path, suffix):
    """The writer writes into the temporary's stream; a failure deletes that temporary."""
    made = []

    def broken(stream):
        np.savez(stream, x=np.arange(3))
        stream.flush()
        made.extend(tmp_path.iterdir())
        raise OSError("No space left on device")

    with pytest.raises(OSError):
        atomic_save(tmp_path / f"target{suffix}", broken, suffix=suffix)
    assert made and list(tmp_path.iterdir()) == []


def test_inputs_key_depends_on_every_part():
    a = np.arange(3.0)
    assert inputs_key("s", a, {"k": 1}) == inputs_key("s", a.copy(), {"k": 1})
    assert inputs_key("s", a, {"k": 1}) != inputs_key("s", a + 1e-12, {"k": 1})
    assert inputs_key("s", a, {"k": 1}) != inputs_key("s", a, {"k": 2})


def test_written_files_get_ordinary_permissions(tmp_path):
    umask = os.umask(0o022)
    try:
        atomic_write_text(tmp_path / "report.html", "x")
    finally:
        os.umask(umask)
    assert (tmp_path / "report.html").stat().st_mode & 0o777 == 0o644
