"""WebConfig: the web controller's settings in one frozen object, built from the keyword form or given whole."""

from __future__ import annotations

import dataclasses
import io

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from asyncdonkey.parts.web import NEW_TOKEN, WebConfig, WebConfigError, WebController
from asyncdonkey.parts.web.auth import is_loopback
from asyncdonkey.parts.web.config import WEB_SETTINGS

QUIET = {"host": "127.0.0.1", "announce": None}


def test_the_keyword_form_and_the_config_form_make_the_same_controller():
    out = io.StringIO()
    by_keywords = WebController(0, "user", modes=("user",), max_throttle=0.4, token="s3cret-token", announce=out)
    config = WebConfig(port=0, mode="user", modes=("user",), max_throttle=0.4, token="s3cret-token", announce=out)
    given_config = WebController(config)
    assert by_keywords.config == given_config.config == config
    assert given_config.config is config  # nothing to apply: the very config
    assert (given_config.port, given_config.mode, given_config.modes, given_config.max_throttle) == (
        0,
        "user",
        ("user",),
        0.4,
    )
    assert given_config.announce is out


def test_keywords_given_with_a_config_are_applied_over_it_and_checked():
    base = WebConfig(port=0, max_throttle=0.5, **QUIET)
    ctr = WebController(base, max_throttle=0.25, idle_release_s=3.0)
    assert ctr.config == dataclasses.replace(base, max_throttle=0.25, idle_release_s=3.0)
    assert ctr.desk.idle_release_s == 3.0
    assert base.max_throttle == 0.5  # the shared config is untouched
    with pytest.raises(WebConfigError, match="max_throttle"):
        WebController(base, max_throttle=2.0)


def test_a_config_is_frozen_and_checked_once_when_made():
    config = WebConfig(**QUIET)
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.port = 1  # type: ignore[misc]
    assert config.token is NEW_TOKEN
    assert WebConfig(mode="pilot", **QUIET).mode == "local"  # Donkeycar's alias, stored canonical
    assert WebConfig(modes=["user", "local_angle"], mode="user", **QUIET).modes == ("user", "local_angle")


def test_an_unknown_setting_is_named():
    with pytest.raises(TypeError, match="'max_trottle'"):
        WebController(max_trottle=0.5, **QUIET)


@pytest.mark.parametrize(
    "bad",
    [
        {"port": 70000},
        {"max_throttle": 1.5},
        {"idle_release_s": 0},
        {"health_every_s": float("nan")},
        {"jpeg_quality": 0},
        {"header_timeout_s": -1},
        {"max_connections": 0},
        {"reserve_fds": -1},
        {"backlog": 0},
    ],
)
def test_each_bad_setting_is_refused_by_the_config_naming_it(bad):
    name = next(iter(bad))
    with pytest.raises(WebConfigError, match=f"WebController: {name}"):
        WebConfig(**QUIET, **bad)
    with pytest.raises(WebConfigError, match=f"WebController: {name}"):
        WebController(**QUIET, **bad)


def test_a_start_mode_outside_the_modes_and_an_unknown_mode_are_refused():
    with pytest.raises(WebConfigError, match="not one of modes"):
        WebConfig(mode="local", modes=("user",), **QUIET)
    with pytest.raises(ValueError, match="WebController modes"):
        WebConfig(modes=("user", "autopilot"), **QUIET)


@settings(max_examples=100, deadline=None)
@given(
    host=st.sampled_from(["127.0.0.1", "::1", "0.0.0.0", "", "::", "192.168.1.20", "localhost", "127.3.4.5"]),
    token=st.one_of(st.none(), st.just(NEW_TOKEN), st.text(min_size=0, max_size=12)),
)
def test_no_config_lets_anyone_drive_without_a_token_beyond_loopback(host, token):
    """The invariant behind ``token=None``: a config without a token exists only for a loopback host, and a
    token is never shorter than 8 characters, however the config is reached (made, or replaced)."""
    allowed = not (token is None and not is_loopback(host)) and not (isinstance(token, str) and len(token) < 8)
    for make in (
        lambda: WebConfig(host=host, token=token),
        lambda: dataclasses.replace(WebConfig(host="127.0.0.1"), host=host, token=token),
        lambda: WebController(host=host, token=token, announce=None).config,
    ):
        if allowed:
            assert make().token == token
        else:
            with pytest.raises(WebConfigError):
                make()


def test_the_controller_keeps_its_state_in_small_objects():
    ctr = WebController(**QUIET)
    assert len(vars(ctr)) <= 20, sorted(vars(ctr))
    assert set(WEB_SETTINGS) >= {"port", "mode", "modes", "host", "token", "max_throttle", "backlog"}
