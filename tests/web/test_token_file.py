"""A token kept in a file: made once, owner-only, the same at every start; a bad file is refused, not replaced."""

from __future__ import annotations

import os
import stat

import pytest

from asyncdonkey.parts.web.auth import WebConfigError, token_from_file


def test_the_first_start_makes_an_owner_only_token_that_later_starts_reuse(tmp_path):
    path = tmp_path / "token"
    first = token_from_file(path)
    assert len(first) >= 16 and path.read_text().strip() == first
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert token_from_file(path) == first == token_from_file(str(path))


def test_a_token_written_by_the_user_is_used_as_it_is(tmp_path):
    path = tmp_path / "token"
    path.write_text("my-own-car-token\n")
    assert token_from_file(path) == "my-own-car-token"


@pytest.mark.parametrize("text", ["", "short", "two words here", "\n\n"])
def test_a_file_without_a_usable_token_is_refused_and_left_alone(tmp_path, text):
    path = tmp_path / "token"
    path.write_text(text)
    with pytest.raises(WebConfigError, match=r"web token file .*token.*at least 8 printable characters"):
        token_from_file(path)
    assert path.read_text() == text


def test_a_missing_folder_is_named(tmp_path):
    with pytest.raises(WebConfigError, match="does not exist"):
        token_from_file(tmp_path / "nope" / "token")
