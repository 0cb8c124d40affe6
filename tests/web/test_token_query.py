"""A script may send the access token as ``?token=`` on a ``GET`` (docs/web.md), and is answered at once.

It used to get a ``302`` to the same URL without the token and a cookie it does not keep, then a ``401``:
``curl 'http://car:8887/status?token=...'`` never worked. A browser opening the printed URL (it accepts HTML)
still gets the cookie and the redirect that takes the token out of its address bar and history.
"""

import aiohttp
import pytest

from ..waiting import await_until
from .web_rig import WebCar, driving

pytestmark = [pytest.mark.realtime, pytest.mark.network]

#: what Chromium and Firefox send when they open a page
BROWSER_ACCEPT = "text/html,application/xhtml+xml,application/xml;q=0.9,*/*;q=0.8"


@pytest.mark.asyncio
async def test_a_script_gets_the_status_with_the_token_in_the_query(tmp_path):
    async with driving(WebCar(tmp_path)) as car, aiohttp.ClientSession() as http:
        url = f"{car.base}/status?token={car.ctr.token}"
        for accept in ("*/*", "application/json", None):  # curl, a JSON client, no Accept at all
            headers = {"Accept": accept or ""}
            async with http.get(url, headers=headers, allow_redirects=False) as r:
                assert r.status == 200, (accept, r.status)
                assert (await r.json())["driveMode"] == "user"
                assert "Set-Cookie" not in r.headers  # a script's token stays its own; nothing to keep
        async with http.get(f"{car.base}/status?token=x{car.ctr.token}", allow_redirects=False) as r:
            assert r.status == 401  # a wrong token is refused as before, with or without the redirect
        async with http.get(f"{car.base}/status?token=", allow_redirects=False) as r:
            assert r.status == 401


@pytest.mark.asyncio
async def test_a_browser_opening_the_printed_url_is_redirected_without_the_token(tmp_path):
    jar = aiohttp.CookieJar(unsafe=True)
    async with driving(WebCar(tmp_path)) as car, aiohttp.ClientSession(cookie_jar=jar) as http:
        for headers in ({"Accept": BROWSER_ACCEPT}, {"Accept": "*/*", "Sec-Fetch-Mode": "navigate"}):
            async with http.get(car.ctr.url, headers=headers, allow_redirects=False) as r:
                assert r.status == 302 and r.headers["Location"] == "/drive"
                assert car.ctr.token not in r.headers["Location"]
                assert "HttpOnly" in r.headers["Set-Cookie"] and "SameSite=Strict" in r.headers["Set-Cookie"]
        async with http.get(f"{car.base}/status") as r:  # the cookie it kept opens the rest
            assert r.status == 200


@pytest.mark.asyncio
async def test_a_post_with_the_token_in_the_query_still_drives(tmp_path):
    async with driving(WebCar(tmp_path)) as car, aiohttp.ClientSession() as http:
        async with http.post(f"{car.base}/drive?token={car.ctr.token}", json={"angle": 0.25}) as r:
            assert r.status == 200
        await await_until(lambda: car.mem.get(["user/angle"]) == [0.25], what="user/angle 0.25")
