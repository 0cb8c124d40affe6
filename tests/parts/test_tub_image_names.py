"""A catalog's image names stay inside the tub's ``images/``: a name that is absolute, has a ``..`` component or
leads out through a symlink is refused (one line naming the tub, the record and the name) by the reader and by
every command that reads tubs, and no file outside the tub is ever read or embedded.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from asyncdonkey.commands.cli import main
from asyncdonkey.parts.tub import Tub, TubFormatError, TubImageError, TubImagePathError
from asyncdonkey.parts.tub.appender import TubAppender

from ..test_replay import write_model

KEY = "cam/image_array"
SECRET_PIXEL = 200  # the outside file's grey level; the tub's frames are 10, 20, 30


def make_tub(root: Path) -> Path:
    """A tub of three 12x16 frames beside ``secret.jpg``, a readable image outside it."""
    app = TubAppender(
        root / "tub", [KEY, "user/angle", "user/throttle"], ["image_array", "float", "float"], fsync=False
    )
    for i in range(3):
        app.write(100.0 + i * 0.05, [np.full((12, 16, 3), 10 * (i + 1), np.uint8), 0.1, 0.2])
    app.close()
    cv2.imwrite(str(root / "secret.jpg"), np.full((12, 16, 3), SECRET_PIXEL, np.uint8))
    return root / "tub"


def set_image_name(tub: Path, index: int, name: str) -> None:
    catalog = tub / "catalog_0.catalog"
    lines = catalog.read_text().splitlines(keepends=True)
    record = json.loads(lines[index])
    record[KEY] = name
    lines[index] = json.dumps(record, sort_keys=True) + "\n"
    catalog.write_text("".join(lines))


def run(*argv: str | Path) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        status = main([str(a) for a in argv])
    return status, err.getvalue()


def escapes(tmp_path: Path) -> dict[str, str]:
    """The three ways out: a ``..`` name, an absolute name, and a symlink inside ``images/`` leading out."""
    os.symlink(tmp_path / "secret.jpg", tmp_path / "tub" / "images" / "link.jpg")
    return {"dotdot": "../../secret.jpg", "absolute": str(tmp_path / "secret.jpg"), "symlink": "link.jpg"}


@pytest.mark.parametrize("way", ["dotdot", "absolute", "symlink"])
def test_the_reader_refuses_an_image_name_leading_out_of_the_tub(tmp_path, way):
    tub = make_tub(tmp_path)
    name = escapes(tmp_path)[way]
    set_image_name(tub, 1, name)
    records = list(Tub(tub))
    assert records[0][KEY][0, 0, 0] == 10  # the others read as before
    with pytest.raises(TubImagePathError) as info:
        records[1][KEY]
    message = str(info.value)
    assert "\n" not in message and str(tub) in message and "record 1" in message and repr(name) in message
    with pytest.raises(TubImagePathError):
        records[1].image_path(KEY)


@pytest.mark.parametrize("way", ["dotdot", "absolute", "symlink"])
def test_replay_convert_and_quantize_stop_on_it_with_one_line_and_embed_nothing(tmp_path, way):
    tub = make_tub(tmp_path)
    name = escapes(tmp_path)[way]
    set_image_name(tub, 2, name)
    model = write_model(tmp_path / "pilot.onnx", 12, 16)
    commands = [
        ("replay", tub, "--pilot", model),
        ("convert", tub, tmp_path / "out.mcap"),
        ("quantize", model, "--tub", tub, "--out", tmp_path / "q.onnx", "--frames", "3"),
    ]
    for argv in commands:
        if argv[0] == "quantize":
            pytest.importorskip("onnxruntime.quantization")
        status, err = run(*argv)
        assert status == 2, (argv[0], err)
        (line,) = err.strip().splitlines()
        assert str(tub) in line and "record 2" in line and repr(name) in line, line
    assert not (tmp_path / "out.mcap").exists()  # the half-written MCAP (with records 0 and 1) was removed


def test_a_symlink_or_subfolder_inside_images_is_still_read(tmp_path):
    tub = make_tub(tmp_path)
    images = tub / "images"
    (images / "sub").mkdir()
    os.rename(images / "0_cam_image_array_.jpg", images / "sub" / "zero.jpg")
    os.symlink("sub/zero.jpg", images / "alias.jpg")
    set_image_name(tub, 0, "alias.jpg")
    set_image_name(tub, 1, "sub/../1_cam_image_array_.jpg")  # '..' refused even when it would stay inside
    records = list(Tub(tub))
    assert records[0][KEY][0, 0, 0] == 10
    with pytest.raises(TubImagePathError):
        records[1][KEY]


def test_a_catalog_path_leading_out_of_the_tub_is_refused(tmp_path):
    tub = make_tub(tmp_path)
    manifest = tub / "manifest.json"
    lines = manifest.read_text().splitlines(keepends=True)
    lines[4] = lines[4].replace('"catalog_0.catalog"', '"../../etc/passwd"')
    manifest.write_text("".join(lines))
    with pytest.raises(TubFormatError, match=r"manifest\.json: catalog path '\.\./\.\./etc/passwd' is not a file name"):
        Tub(tub)
    status, err = run("replay", tub, "--pilot", write_model(tmp_path / "pilot.onnx", 12, 16))
    assert status == 2 and err.count("\n") == 1 and "etc/passwd" in err


NAME_PARTS = st.sampled_from(["..", ".", "", "images", "tub", "secret.jpg", "link", "0_cam_image_array_.jpg"])


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(parts=st.lists(NAME_PARTS, min_size=1, max_size=5), absolute=st.booleans())
def test_no_image_name_reads_a_file_outside_the_tub(tmp_path_factory, parts, absolute):
    root = tmp_path_factory.mktemp("names")
    tub = make_tub(root)
    os.symlink(root, tub / "images" / "link")  # a symlinked folder leading out
    name = ("/" if absolute else "") + "/".join(parts)
    if absolute:
        name = str(root) + name
    set_image_name(tub, 0, name)
    (record, *_) = Tub(tub)
    try:
        image = record[KEY]
    except TubImagePathError as exc:
        assert repr(name) in str(exc)
    except TubImageError:
        pass  # inside images/ but no image there (a folder, a missing file)
    else:
        assert image[0, 0, 0] != SECRET_PIXEL
        resolved = (tub / "images" / name).resolve()
        assert resolved.is_relative_to((tub / "images").resolve()) and ".." not in Path(name).parts
