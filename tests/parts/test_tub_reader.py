"""Tub (the reader): clear errors for what is not a tub, lazy images, deletion persisted, odd catalogs."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from asyncdonkey.parts.tub import (
    Tub,
    TubFormatError,
    TubImageError,
    TubNotFoundError,
    TubWiper,
    TubWriter,
    load_image,
)


def scene(k: int) -> np.ndarray:
    yy, xx = np.mgrid[0:120, 0:160]
    return np.dstack([(xx + 5 * k) % 256, (2 * yy) % 256, np.full_like(xx, 30 * k % 256)]).astype(np.uint8)


def make_tub(path: Path, n: int = 6, max_len: int = 1000) -> Path:
    w = TubWriter(path, ["cam/image_array", "user/angle"], ["image_array", "float"], max_catalog_len=max_len)
    for i in range(n):
        w.run(scene(i), i / 10)
    w.shutdown()
    return path


# ------------------------------------------------------------------------------------------------ errors
def test_not_a_tub_errors_name_the_path(tmp_path):
    with pytest.raises(TubNotFoundError, match=f"{tmp_path / 'nope'}: no such tub directory"):
        Tub(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(TubNotFoundError, match=r"empty: not a tub \(no manifest\.json\)"):
        Tub(tmp_path / "empty")
    with pytest.raises(FileNotFoundError):  # TubNotFoundError is a FileNotFoundError too
        Tub(tmp_path / "empty")


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('["a"]\n["float"]\n{}\n', r"expected 5 JSON lines .* found 3"),
        ('["a"]\n["float"]\n{}\n{}\n{"paths": ["catalog_0.catalog"], "current_in', r"line 5 .* not valid JSON"),
        ('["a"]\n["float", "int"]\n{}\n{}\n{"paths": [], "current_index": 0, "max_len": 5}\n', r"1 inputs but 2"),
        ('["a"]\n["float"]\n{}\n{}\n{"paths": [], "max_len": 5}\n', r"no 'current_index'"),
        ('["a"]\n["float"]\n[]\n{}\n{"paths": [], "current_index": 0, "max_len": 5}\n', r"line 3"),
    ],
    ids=["torn", "torn-last-line", "types", "no-index", "metadata"],
)
def test_corrupt_manifest_errors_name_the_file_and_what_was_expected(tmp_path, content, message):
    (tmp_path / "manifest.json").write_text(content)
    with pytest.raises(TubFormatError, match=message) as info:
        Tub(tmp_path)
    assert str(tmp_path / "manifest.json") in str(info.value)


# ------------------------------------------------------------------------------------------- records
def test_records_are_mappings_with_lazily_loaded_rgb_images(tmp_path):
    root = make_tub(tmp_path / "t", n=3)
    tub = Tub(root)
    assert len(tub) == 3 and tub.indexes() == [0, 1, 2]
    records = list(tub)
    # nothing decoded yet: the images can even disappear until someone asks for them
    os.remove(root / "images" / "2_cam_image_array_.jpg")
    r0 = records[0]
    assert r0.index == r0["_index"] == 0
    assert set(r0) == {"_index", "_session_id", "_timestamp_ms", "cam/image_array", "user/angle"}
    assert "cam/image_array" in r0 and len(r0) == 5
    img = r0["cam/image_array"]
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8
    assert np.abs(img.astype(int) - scene(0)).mean() < 3
    assert r0["cam/image_array"] is img  # loaded once
    assert r0.raw["cam/image_array"] == "0_cam_image_array_.jpg"
    assert r0.image_path("cam/image_array") == root / "images" / "0_cam_image_array_.jpg"
    assert records[1].get("user/angle") == 0.1 and records[1].get("missing", "x") == "x"
    with pytest.raises(TubImageError, match=r"2_cam_image_array_\.jpg: image file is missing"):
        records[2]["cam/image_array"]
    assert records[2]["user/angle"] == 0.2  # the rest of the record still reads
    (root / "images" / "1_cam_image_array_.jpg").write_bytes(b"")  # e.g. zero bytes after a power cut
    with pytest.raises(TubImageError, match=r"1_cam_image_array_\.jpg: not a readable image"):
        records[1]["cam/image_array"]


def test_delete_and_restore_are_persisted(tmp_path):
    root = make_tub(tmp_path / "t", n=8, max_len=3)
    tub = Tub(root)
    tub.delete_records([1, 2, 6])
    tub.restore_records(2)
    assert tub.deleted_indexes == {1, 6}
    assert len(tub) == 6 and [r.index for r in tub] == [0, 2, 3, 4, 5, 7]
    assert [r.index for r in tub.records(include_deleted=True)] == list(range(8))
    again = Tub(root)
    assert again.deleted_indexes == {1, 6} and len(again) == 6
    catalog_meta = json.loads((root / "manifest.json").read_text().splitlines()[4])
    assert catalog_meta["deleted_indexes"] == [1, 6] and catalog_meta["current_index"] == 8
    assert again.delete_last_n_records(3) == [4, 5, 7]  # the last three not yet deleted
    assert Tub(root).indexes() == [0, 2, 3]
    assert not list(root.glob("*.tmp"))


def test_tub_wiper_works_on_a_reader_tub_too(tmp_path):
    tub = Tub(make_tub(tmp_path / "t", n=5))
    wiper = TubWiper(tub, num_records=2)
    for pressed in (True, True, False, True):
        wiper.run(pressed)
    assert tub.deleted_indexes == {1, 2, 3, 4}
    with pytest.raises(ValueError, match="num_records"):
        TubWiper(tub, num_records=0)


def test_metadata_sessions_and_repr(tmp_path):
    root = make_tub(tmp_path / "t", n=2)
    tub = Tub(root)
    assert tub.max_len == 1000 and tub.metadata == {}
    assert len(tub.sessions) == 1 and "created_at" in tub.manifest_metadata
    assert "records=2" in repr(tub) and "_index" in repr(next(iter(tub)))


# --------------------------------------------------------------------------------------- odd catalogs
def test_a_corrupt_middle_line_keeps_later_indexes_and_is_counted(tmp_path):
    root = make_tub(tmp_path / "t", n=4)
    cat = root / "catalog_0.catalog"
    lines = cat.read_bytes().splitlines(keepends=True)
    lines[1] = b"\x00" * (len(lines[1]) - 1) + b"\n"  # zeros where a line was (power cut, unsynced block)
    lines[2] = b"{not json}\n"
    cat.write_bytes(b"".join(lines))
    tub = Tub(root)
    assert tub.corrupt_lines == 1 and len(tub) == 3  # the zero line is found when opening
    assert [r.index for r in tub] == [0, 3]  # the bad JSON is found when reading
    assert tub.corrupt_lines == 2


def test_a_torn_last_line_is_skipped_and_counted(tmp_path):
    root = make_tub(tmp_path / "t", n=3)
    with open(root / "catalog_0.catalog", "ab") as f:
        f.write(b'{"_index": 3, "_session_id": "x", "user/an')
    tub = Tub(root)
    assert tub.torn_lines == 1 and len(tub) == 3
    assert [r.index for r in tub] == [0, 1, 2]


def test_records_in_a_catalog_not_yet_listed_are_found(tmp_path):
    root = make_tub(tmp_path / "t", n=4, max_len=2)
    m = (root / "manifest.json").read_text().splitlines()
    meta = json.loads(m[4])
    meta["paths"] = meta["paths"][:1]  # as if the writer died before listing catalog_1
    meta["current_index"] = 2
    m[4] = json.dumps(meta)
    (root / "manifest.json").write_text("\n".join(m) + "\n")
    (root / "catalog_1.catalog_manifest").unlink()
    tub = Tub(root)
    assert tub.unlisted_catalogs == ["catalog_1.catalog"]
    assert [r.index for r in tub] == [0, 1, 2, 3]
    assert [r["user/angle"] for r in tub] == [0.0, 0.1, 0.2, 0.3]


def test_a_missing_listed_catalog_is_reported_not_fatal(tmp_path):
    root = make_tub(tmp_path / "t", n=4, max_len=2)
    (root / "catalog_0.catalog").unlink()
    tub = Tub(root)
    assert tub.missing_catalogs == ["catalog_0.catalog"]
    assert [r.index for r in tub] == [2, 3]  # catalog_1 keeps its start_index


def test_load_image_returns_rgb_like_donkeycar(tmp_path):
    from PIL import Image

    img = scene(3)
    Image.fromarray(img).save(tmp_path / "x.png")
    np.testing.assert_array_equal(load_image(tmp_path / "x.png"), img)
    rgba = np.dstack([img, np.full(img.shape[:2], 200, np.uint8)])
    Image.fromarray(rgba).save(tmp_path / "y.png")
    np.testing.assert_array_equal(load_image(tmp_path / "y.png"), rgba)
