"""A token kept in a file: made once, owner-only, the same at every start; a bad file is refused, not replaced.

The token is a password: an existing file must be a regular file of the user running the car with no group or
other bits, reached without a symbolic link; anything else is refused in one line naming the file, what is wrong
and the fix.
"""

from __future__ import annotations

import os
import pwd
import stat
import threading

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey.parts.web.auth import WebConfigError, token_from_file


def private(path, text="my-own-car-token\n"):
    """A token file as the docs tell the user to make it: written, then ``chmod 600``."""
    path.write_text(text)
    path.chmod(0o600)
    return path


def refusal(path) -> str:
    with pytest.raises(WebConfigError) as info:
        token_from_file(path)
    message = str(info.value)
    assert "\n" not in message and repr(str(path)) in message
    return message


def test_the_first_start_makes_an_owner_only_token_that_later_starts_reuse(tmp_path):
    path = tmp_path / "token"
    first = token_from_file(path)
    assert len(first) >= 16 and path.read_text().strip() == first
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert token_from_file(path) == first == token_from_file(str(path))


def test_a_new_token_file_is_owner_only_whatever_the_umask(tmp_path):
    old = os.umask(0)
    try:
        token_from_file(tmp_path / "token")
    finally:
        os.umask(old)
    assert stat.S_IMODE(os.stat(tmp_path / "token").st_mode) == 0o600


def test_a_private_token_written_by_the_user_is_used_as_it_is(tmp_path):
    assert token_from_file(private(tmp_path / "token")) == "my-own-car-token"


@pytest.mark.parametrize("text", ["", "short", "two words here", "\n\n", "x" * 5000])
def test_a_file_without_a_usable_token_is_refused_and_left_alone(tmp_path, text):
    path = private(tmp_path / "token", text)
    with pytest.raises(WebConfigError, match=r"web token file .*token.*at least 8 printable characters"):
        token_from_file(path)
    assert path.read_text() == text


def test_a_binary_file_is_refused_in_one_line(tmp_path):
    path = tmp_path / "token"
    path.write_bytes(b"\xff\xfebinary-not-a-token")  # not UTF-8: no token, however printable the rest
    path.chmod(0o600)
    assert "at least 8 printable characters" in refusal(path)


def test_a_missing_folder_is_named(tmp_path):
    with pytest.raises(WebConfigError, match="does not exist"):
        token_from_file(tmp_path / "nope" / "token")


def test_a_token_file_others_can_read_is_refused_with_the_chmod_that_fixes_it(tmp_path):
    path = private(tmp_path / "token")
    path.chmod(0o666)
    message = refusal(path)
    assert "mode 0666" in message and f"chmod 600 {path}" in message
    path.chmod(0o600)  # the fix the message gives
    assert token_from_file(path) == "my-own-car-token"


@settings(max_examples=60, deadline=None)
@given(mode=st.integers(0o400, 0o777))
def test_any_group_or_other_bit_is_refused_and_owner_bits_alone_are_accepted(tmp_path_factory, mode):
    path = private(tmp_path_factory.mktemp("mode") / "token")
    path.chmod(mode)
    if mode & 0o077:
        assert f"mode {mode:04o}" in refusal(path)
    else:
        assert token_from_file(path) == "my-own-car-token"


def test_a_symbolic_link_is_not_followed_even_to_a_good_token_file(tmp_path):
    target = private(tmp_path / "real-token")
    link = tmp_path / "token"
    link.symlink_to(target)
    assert "symbolic link" in refusal(link)


def test_a_link_to_a_system_file_never_makes_it_the_token(tmp_path):
    link = tmp_path / "token"
    link.symlink_to("/etc/hostname" if os.path.exists("/etc/hostname") else "/etc/passwd")
    assert "symbolic link" in refusal(link)


def test_a_dangling_link_is_refused_and_nothing_is_created_through_it(tmp_path):
    link = tmp_path / "token"
    link.symlink_to(tmp_path / "elsewhere")
    assert "symbolic link" in refusal(link)
    assert not (tmp_path / "elsewhere").exists()


def test_a_directory_is_refused(tmp_path):
    (tmp_path / "token").mkdir(mode=0o700)
    assert "is a directory" in refusal(tmp_path / "token")


def test_a_fifo_is_refused_without_waiting_for_a_writer(tmp_path):
    path = tmp_path / "token"
    os.mkfifo(path, 0o600)
    done: list[str] = []
    t = threading.Thread(target=lambda: done.append(refusal(path)), daemon=True)
    t.start()
    t.join(5)
    assert done and "not a regular file" in done[0]


@pytest.mark.skipif(os.geteuid() != 0, reason="only root can give a file to another user")
def test_a_file_of_another_user_is_refused_with_the_chown_that_fixes_it(tmp_path):
    path = private(tmp_path / "token")
    nobody = pwd.getpwnam("nobody").pw_uid
    os.chown(path, nobody, -1)
    message = refusal(path)
    assert f"owned by uid {nobody}" in message and f"chown {os.geteuid()} {path}" in message
