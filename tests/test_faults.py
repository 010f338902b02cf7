"""Fault injection: each probe ends in one clear error (StageError/ValueError naming the file or
parameter) and leaves every downstream artifact as it was."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import zarr

from stages.io import StageError, atomic_dir, create_array, open_zarr


def _store(path: Path, n: int = 40) -> np.ndarray:
    """A sealed image store like datasets/render/images.zarr: (n, 9, 16, 3) uint8 in chunks of 8."""
    images = np.random.default_rng(0).integers(1, 255, (n, 9, 16, 3), dtype=np.uint8)
    with atomic_dir(path) as tmp:
        create_array(zarr.open_group(str(tmp), mode="w"), "images", data=images, chunks=(8, 9, 16, 3))
    return images


def test_sealed_store_reads_back(tmp_path):
    images = _store(tmp_path / "images.zarr")
    np.testing.assert_array_equal(open_zarr(tmp_path / "images.zarr")["images"][:], images)


def test_missing_chunk_is_named(tmp_path):
    _store(tmp_path / "images.zarr")
    (tmp_path / "images.zarr/images/c/2/0/0/0").unlink()
    with pytest.raises(StageError, match=r"images.zarr is missing chunk images/c/2/0/0/0"):
        open_zarr(tmp_path / "images.zarr", "image store")


@pytest.mark.parametrize("byte", [0, -5, "middle"])
def test_flipped_bit_is_named(tmp_path, byte):
    _store(tmp_path / "images.zarr")
    chunk = tmp_path / "images.zarr/images/c/1/0/0/0"
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2 if byte == "middle" else byte] ^= 0x10
    chunk.write_bytes(bytes(raw))
    with pytest.raises(StageError, match=r"chunk images/c/1/0/0/0 fails its crc32c checksum"):
        open_zarr(tmp_path / "images.zarr", "image store")


def test_unsealed_or_extended_store_is_refused(tmp_path):
    zarr.open_group(str(tmp_path / "raw.zarr"), mode="w").create_array("x", data=np.arange(4))
    with pytest.raises(StageError, match="has no checksum manifest"):
        open_zarr(tmp_path / "raw.zarr")
    _store(tmp_path / "images.zarr")
    create_array(zarr.open_group(str(tmp_path / "images.zarr"), mode="a"), "extra", data=np.arange(4))
    with pytest.raises(StageError, match=r"arrays \['extra'\] differ from its checksum manifest"):
        open_zarr(tmp_path / "images.zarr")


def test_a_failed_write_leaves_the_old_store(tmp_path):
    images = _store(tmp_path / "images.zarr")
    with pytest.raises(RuntimeError, match="never written"):
        with atomic_dir(tmp_path / "images.zarr") as tmp:  # a writer that fills only half the array
            create_array(zarr.open_group(str(tmp), mode="w"), "images", shape=(40, 9, 16, 3),
                         chunks=(8, 9, 16, 3), dtype="uint8")[:16] = 0
    np.testing.assert_array_equal(open_zarr(tmp_path / "images.zarr")["images"][:], images)
    assert [p.name for p in tmp_path.iterdir()] == ["images.zarr"]
