"""A checkpoint's files: the manifest reads back and checks itself, files are written
whole and never over another, reads verify size and CRC-32."""

from __future__ import annotations

import zlib
from pathlib import Path

import pytest

from dqnlab.run.checkpoint_chunks import changed_chunks
from dqnlab.run.checkpoint_files import read_verified, write_file
from dqnlab.run.checkpoint_manifest import ArrayRecord, FileRecord, Incomplete, Manifest


def test_a_manifest_reads_back_and_catches_a_flipped_digit() -> None:
    chunk = FileRecord("frames.00000.g000000001.bin", 64, 0xDEADBEEF)
    manifest = Manifest(
        step=250,
        generation=1,
        dqnlab_version="0.1.0",
        config_fingerprint="ab" * 32,
        state=FileRecord("state.pt", 10, 7),
        arrays={"frames": ArrayRecord("|u1", (4, 16), 4, (chunk,))},
    )
    text = manifest.to_json()
    assert Manifest.from_json(text) == manifest
    with pytest.raises(Incomplete, match="fails its own checksum"):
        Manifest.from_json(text.replace(b'"step": 250', b'"step": 251'))
    with pytest.raises(Incomplete, match="unreadable"):
        Manifest.from_json(b"{")


def test_files_are_written_whole_and_verified_when_read(tmp_path: Path) -> None:
    data = bytes(range(256)) * 3
    created: list[Path] = []
    record = write_file(tmp_path / "chunk.bin", [memoryview(data)], created)
    assert record == FileRecord("chunk.bin", len(data), zlib.crc32(data))
    assert not list(tmp_path.glob("*.tmp"))
    target = bytearray(len(data))
    read_verified(tmp_path / "chunk.bin", record, memoryview(target))
    assert bytes(target) == data
    with pytest.raises(FileExistsError):
        write_file(tmp_path / "chunk.bin", [memoryview(data)], [])
    flipped = bytearray(data)
    flipped[100] ^= 1
    (tmp_path / "chunk.bin").write_bytes(flipped)
    with pytest.raises(Incomplete, match="CRC-32"):
        read_verified(tmp_path / "chunk.bin", record)
    (tmp_path / "chunk.bin").write_bytes(data[:-1])
    with pytest.raises(Incomplete, match="bytes, the manifest says"):
        read_verified(tmp_path / "chunk.bin", record)


def test_changed_chunks_of_a_ring_range() -> None:
    assert changed_chunks(None, 100, 10) is None
    assert changed_chunks((15, 25), 100, 10) == {1, 2}
    assert changed_chunks((95, 5), 100, 10) == {9, 0}  # wraps around
    assert changed_chunks((30, 30), 100, 10) == set()
