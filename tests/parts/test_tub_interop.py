"""Interop with Donkeycar 5.3 itself: its reader opens our tubs, ours opens its tubs, either appends to the
other's, and the files look the same."""

from __future__ import annotations

import contextlib
import io
import json
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from asyncdonkey.parts.tub import Tub, TubWiper, TubWriter

pytestmark = [pytest.mark.donkeycar]

with contextlib.redirect_stdout(io.StringIO()):  # Donkeycar prints a banner on import
    from donkeycar.parts.tub_v2 import Tub as DkTub
    from donkeycar.parts.tub_v2 import TubWriter as DkTubWriter

INPUTS = ["cam/image_array", "user/angle", "user/throttle", "user/mode", "rec", "n", "arr", "lst", "vec"]
TYPES = ["image_array", "float", "float", "str", "boolean", "int", "nparray", "list", "vector"]


def scene(k: int) -> np.ndarray:
    yy, xx = np.mgrid[0:120, 0:160]
    return np.dstack([(xx + 4 * k) % 256, (2 * yy + k) % 256, np.full_like(xx, 20 * k % 256)]).astype(np.uint8)


def values(i: int) -> tuple:
    return (scene(i), i / 20 - 0.5, 0.3, "user" if i % 3 else "local", i % 2 == 0, i, np.arange(2.0) * i,
            [i, i + 1], [0.5, float(i)])  # fmt: skip


def pil_rgb(path: Path) -> np.ndarray:
    """An image as Donkeycar's training pipeline loads it (PIL)."""
    return np.asarray(Image.open(path).convert("RGB"))


def dk_records(path: Path, read_only: bool) -> tuple[int, list[dict]]:
    tub = DkTub(str(path), read_only=read_only)
    try:
        return len(tub), list(tub)
    finally:
        tub.close()


@pytest.mark.parametrize("read_only", [True, False], ids=["read_only", "read_write"])
def test_donkeycar_reads_our_tub(tmp_path, read_only):
    root = tmp_path / "ours"
    w = TubWriter(root, INPUTS, TYPES, metadata=["car:sim"], max_catalog_len=10)
    for i in range(25):
        w.run(*values(i))
    w.delete_records([3, 17])
    w.shutdown()

    n, dk = dk_records(root, read_only)
    ours = list(Tub(root))
    assert n == len(ours) == 23
    assert [r["_index"] for r in dk] == [r.index for r in ours] == [i for i in range(25) if i not in (3, 17)]
    assert dk == [r.raw for r in ours]  # every field, as stored
    for rec in dk[:4]:
        i = rec["_index"]
        assert rec["user/angle"] == pytest.approx(i / 20 - 0.5) and rec["arr"] == [0.0, float(i)]
        dk_img = pil_rgb(root / "images" / rec["cam/image_array"])
        assert np.abs(dk_img.astype(int) - scene(i)).mean() < 3
        ours_img = next(r for r in ours if r.index == i)["cam/image_array"]
        assert np.abs(dk_img.astype(int) - ours_img).mean() < 1  # both decoders agree
    if not read_only:
        mm = DkTub(str(root)).manifest
        assert mm.metadata == {"car": "sim"} and mm.current_index == 25 and mm.deleted_indexes == {3, 17}
        assert mm.manifest_metadata["sessions"]["last_full_id"] == dk[0]["_session_id"]
        mm.close()


def test_we_read_a_donkeycar_tub_with_images_and_deletions(tmp_path):
    root = tmp_path / "dk"
    dw = DkTubWriter(str(root), inputs=INPUTS, types=TYPES, metadata=["track:home"], max_catalog_len=10)
    for i in range(25):
        dw.run(*values(i))
    dw.tub.delete_records([2, 12])
    TubWiper(dw.tub, num_records=3).run(True)  # our wiper on Donkeycar's tub: deletes 22, 23, 24
    dw.close()

    tub = Tub(root)
    assert tub.inputs == INPUTS and tub.types == TYPES and tub.metadata == {"track": "home"}
    assert tub.deleted_indexes == {2, 12, 22, 23, 24}
    assert len(tub) == 20 and tub.torn_lines == tub.corrupt_lines == 0
    recs = list(tub)
    expected = [i for i in range(22) if i not in (2, 12)]
    assert [r.index for r in recs] == expected
    for r in recs:
        i = r.index
        v = values(i)
        assert (r["user/angle"], r["user/mode"], r["rec"], r["n"]) == (v[1], v[3], v[4], v[5])
        assert r["arr"] == [0.0, float(i)] and r["lst"] == [i, i + 1] and r["vec"] == [0.5, float(i)]
        assert r["_session_id"] == tub.sessions[0]
    for r in recs[:3]:
        img = r["cam/image_array"]
        assert img.shape == (120, 160, 3) and img.dtype == np.uint8
        assert np.abs(img.astype(int) - scene(r.index)).mean() < 3  # RGB as Donkeycar meant it
        assert np.abs(img.astype(int) - pil_rgb(r.image_path("cam/image_array"))).mean() < 1


def test_each_appends_to_the_others_tub_as_a_new_session(tmp_path):
    root = tmp_path / "shared"
    dw = DkTubWriter(str(root), inputs=INPUTS, types=TYPES, max_catalog_len=4)
    for i in range(6):
        dw.run(*values(i))
    dw.close()
    w = TubWriter(root, INPUTS, TYPES)
    assert w.run(*values(6)) == 6  # Donkeycar's six: ours continues its count (this record is only queued)
    w.run(*values(7))
    w.shutdown()
    dw = DkTubWriter(str(root), inputs=INPUTS, types=TYPES)
    dw.run(*values(8))
    dw.close()

    n, dk = dk_records(root, read_only=True)
    ours = list(Tub(root))
    assert n == len(ours) == 9
    assert [r["_index"] for r in dk] == [r.index for r in ours] == list(range(9))
    assert [r["_session_id"][-2:] for r in dk] == ["_0"] * 6 + ["_1"] * 2 + ["_2"]
    assert Tub(root).sessions == [dk[0]["_session_id"], dk[6]["_session_id"], dk[8]["_session_id"]]


def test_our_files_look_like_donkeycars(tmp_path):
    dw = DkTubWriter(str(tmp_path / "dk"), inputs=INPUTS, types=TYPES, metadata=["a:b"], max_catalog_len=3)
    w = TubWriter(tmp_path / "ours", INPUTS, TYPES, metadata=["a:b"], max_catalog_len=3)
    for i in range(5):
        dw.run(*values(i))
        w.run(*values(i))
    dw.close()
    w.shutdown()

    def listing(p: Path) -> list[str]:
        return sorted(str(f.relative_to(p)) for f in p.rglob("*"))

    assert listing(tmp_path / "ours") == listing(tmp_path / "dk")
    ours_m = (tmp_path / "ours" / "manifest.json").read_text().splitlines()
    dk_m = (tmp_path / "dk" / "manifest.json").read_text().splitlines()
    assert ours_m[:3] == dk_m[:3]  # inputs, types, metadata byte for byte
    assert json.loads(ours_m[4]) == json.loads(dk_m[4])
    assert set(json.loads(ours_m[3])) == set(json.loads(dk_m[3])) == {"created_at", "sessions"}
    for n in range(2):
        for suffix in ("catalog", "catalog_manifest"):
            a = [json.loads(x) for x in (tmp_path / "ours" / f"catalog_{n}.{suffix}").read_text().splitlines()]
            b = [json.loads(x) for x in (tmp_path / "dk" / f"catalog_{n}.{suffix}").read_text().splitlines()]
            for x, y in zip(a, b, strict=True):
                for k in ("_timestamp_ms", "created_at"):
                    x.pop(k, None), y.pop(k, None)
                assert x == y
    sizes = [os.path.getsize(tmp_path / d / "images" / "0_cam_image_array_.jpg") for d in ("ours", "dk")]
    assert 0.7 < sizes[0] / sizes[1] < 1.4  # same JPEG quality (75) as Donkeycar's PIL


def test_donkeycar_cannot_write_gray16_but_we_can(tmp_path):
    """Donkeycar 5.3 calls ``_image_file_name(..., ext='.png')`` but the parameter is ``extension``."""
    dw = DkTubWriter(str(tmp_path / "dk"), inputs=["depth"], types=["gray16_array"])
    with pytest.raises(TypeError, match="ext"):
        dw.run(np.zeros((4, 4), np.uint16))
    dw.close()
    w = TubWriter(tmp_path / "ours", ["depth"], ["gray16_array"])
    w.run(np.full((4, 4), 40_000, np.uint16))
    w.shutdown()
    (rec,) = dk_records(tmp_path / "ours", read_only=True)[1]
    assert rec["depth"] == "0_depth_.png"
    assert np.asarray(Image.open(tmp_path / "ours" / "images" / "0_depth_.png")).max() == 40_000
