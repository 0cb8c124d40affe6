"""A standby pilot server: who answers, decided from Zenoh liveliness tokens (``asyncdonkey.parts.zenoh.standby``).

The rule alone on a controlled timeline (fake token events; a pair simulated with a propagation delay, checked
with hypothesis: after they settle exactly one answers, and a returning primary never answers beside the
standby); what ``zenoh-pair --fleet --standby`` writes (both CNs in each car's rules, both endpoints, the
servers' mutual rules); the car's duplicate rule (the first answer of a frame kept, the second counted, the age
true); in one process, the split (both answer: every second answer counted, ages true); and as processes, four
cars on a primary and a standby: kill -9 of the primary and every car keeps being commanded within its failsafe
window, no frame answered twice while both run, the primary back without a double answer; SIGSTOP of the
primary and each car's failsafe stops it until the standby, told by the lease, drives it.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import signal
import time
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from asyncdonkey.commands.cli import main
from asyncdonkey.parts.zenoh.standby import (
    AnswerRule,
    ServerRole,
    StandbyConfigError,
    alive_key,
    answering_key,
    role_for,
    role_from_config,
)

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "examples" / "models"
FAILSAFE_S = 0.25


def _json5(path: Path) -> dict:
    return json.loads(path.read_text().split("\n", 1)[1])  # first line is a // comment


# -- the rule, on a controlled timeline ----------------------------------------------------------------------
def test_a_server_decides_after_its_grace_and_answers_while_the_watched_token_is_absent():
    rule = AnswerRule(start=10.0, grace_s=1.0)
    assert not rule.answering(10.5)  # undecided: it has not watched long enough to know
    assert rule.answering(11.0)  # nothing appeared within the grace: the other is not there
    assert not rule.token(True, 12.0)  # the other's token appears: stop
    assert rule.token(False, 13.0)  # and goes: answer again
    assert rule.switches == [(11.0, True), (12.0, False), (13.0, True)]
    early = AnswerRule(start=0.0, grace_s=1.0)
    assert not early.token(True, 0.1) and not early.answering(5.0)  # seen during the grace: never answers
    assert early.token(False, 6.0) and early.switches == [(6.0, True)]
    with pytest.raises(ValueError, match="grace_s"):
        AnswerRule(0.0, grace_s=-1)


def test_a_query_decides_a_primary_at_once_and_a_standby_only_when_the_token_is_there():
    primary = AnswerRule(start=0.0, grace_s=1.0)
    assert primary.queried(False, 0.1, decides_absence=True)  # no standby answering: the primary answers now
    assert not primary.queried(True, 0.2, decides_absence=True)  # a later query finds it: stop
    standby = AnswerRule(start=0.0, grace_s=1.0)
    assert not standby.queried(False, 0.1, decides_absence=False)  # it may not have reached its primary yet
    assert standby.answering(1.0)  # its grace decides
    assert not standby.queried(True, 1.5, decides_absence=False)  # a query finds the primary: stop


def test_a_server_back_from_an_absence_relearns_before_it_answers_again():
    primary = AnswerRule(start=0.0, grace_s=1.0, away_s=2.0)
    assert primary.queried(False, 0.1, decides_absence=True)  # decided: no standby answering
    assert primary.answering(1.1) and primary.answering(2.1)  # consulted every second: it answers on
    # frozen 4 s: back, it answers nothing on what it knew before, and a query's absence does not decide
    assert not primary.answering(6.1) and primary.away == [(6.1, pytest.approx(4.0))]
    assert not primary.queried(False, 6.15, decides_absence=True)
    assert not primary.token(True, 6.2)  # the standby took over meanwhile: its token reaches it
    assert not primary.answering(7.5)  # decided by the token: no answer while it is there, grace or not
    assert primary.token(False, 7.6)  # the standby hands back
    assert primary.switches == [(0.1, True), (6.1, False), (7.6, True)]
    alone = AnswerRule(start=0.0, grace_s=1.0, away_s=2.0)
    assert alone.answering(1.0) and not alone.answering(4.0)  # away: undecided again ...
    assert not alone.answering(4.9) and alone.answering(5.0)  # ... until a grace passes with no token
    assert not alone.relearning and alone.queried(False, 5.5, decides_absence=True)
    # the standby's answering token withdrawn before the resumed primary's session heard of it: its running token
    # reappearing says the sessions are back, and a query sent from then on decides, long before the grace (6.0)
    resumed = AnswerRule(start=0.0, grace_s=1.0, away_s=2.0)
    assert resumed.answering(1.0) and not resumed.answering(5.0)
    assert not resumed.queried(False, 5.01, decides_absence=True)  # the sessions are not back: nothing decided
    assert not resumed.running(True, 5.05) and resumed.reached
    assert resumed.queried(False, 5.07, decides_absence=True)  # asked once reached: no answering token, answer
    late = AnswerRule(start=0.0, grace_s=1.0, away_s=2.0)
    assert late.answering(1.0) and not late.answering(5.0)
    late.running(True, 5.05)
    assert not late.queried(True, 5.07, decides_absence=True)  # the standby still answers: wait for it to stop
    assert not late.answering(5.5) and late.token(False, 5.6)
    gone = AnswerRule(start=0.0, grace_s=1.0, away_s=2.0)  # the answering token never seen, its withdrawal is
    assert gone.answering(1.0) and not gone.answering(5.0)
    assert not gone.token(False, 5.02)  # before the sessions are back: the closing of the old one, decides nothing
    gone.running(True, 5.05)
    assert gone.token(False, 5.1)  # once reached: the standby's own withdrawal, so the primary answers
    assert not AnswerRule(0.0, 1.0).running(True, 0.1)  # not relearning: the running token decides nothing
    with pytest.raises(ValueError, match="away_s"):
        AnswerRule(0.0, grace_s=1.0, away_s=0.5)


def test_a_query_is_overtaken_by_the_watched_tokens_events_and_by_the_running_token_only_while_relearning():
    # a starting primary queries at once; its subscriber's history brings the standby's running token meanwhile,
    # which says nothing about whether the standby answers: the query still decides (no 1 s grace for the cars)
    starting = AnswerRule(start=0.0, grace_s=1.0, away_s=2.0)
    asked = starting.asking()
    assert not starting.running(True, 0.01)
    assert starting.queried(False, 0.02, decides_absence=True, asked=asked)
    # an event of the watched token is newer than any query sent before it
    overtaken = AnswerRule(start=0.0, grace_s=1.0, away_s=2.0)
    asked = overtaken.asking()
    assert not overtaken.token(True, 0.01)  # the standby answers
    assert not overtaken.queried(False, 0.02, decides_absence=True, asked=asked)  # an older view: ignored
    assert overtaken.present and overtaken.queried(False, 0.03, decides_absence=True, asked=overtaken.asking())
    # relearning, a query sent before the running token's return was answered from the view before the absence
    resumed = AnswerRule(start=0.0, grace_s=1.0, away_s=2.0)
    assert resumed.answering(1.0) and not resumed.answering(5.0)
    asked = resumed.asking()
    resumed.running(True, 5.05)
    assert not resumed.queried(False, 5.06, decides_absence=True, asked=asked) and not resumed.decided
    assert resumed.queried(False, 5.07, decides_absence=True, asked=resumed.asking())


def test_roles_name_the_keys_each_server_watches():
    primary, standby = ServerRole("gpu1", standby="gpu2"), ServerRole("gpu2", primary="gpu1")
    assert primary.watched == answering_key("gpu1") == "pilot-servers/gpu1/standby-answering"
    assert standby.watched == alive_key("gpu1") == "pilot-servers/gpu1/alive"
    with pytest.raises(StandbyConfigError, match="standby of itself"):
        ServerRole("gpu1", primary="gpu1")


class _Pair:
    """A primary and a standby whose tokens reach each other ``delay`` s after they change (a simulation of
    :class:`RoleWatch` on a link that carries them), on a timeline of 1 ms steps. The primary's liveliness query
    after the standby's running token reappears (and a starting primary's, sent at once) takes ``delay`` each way
    and is answered by the standby; the primary's rule drops an answer an event overtook, as in the pilot server."""

    def __init__(self, grace_s: float, delay: float, away_s: float = math.inf) -> None:
        self.grace_s, self.delay, self.away_s = grace_s, delay, away_s
        self.primary: AnswerRule | None = AnswerRule(0.0, grace_s, away_s)
        self.standby = AnswerRule(0.0, grace_s)
        self.inbox: list[tuple[float, str, Any]] = [(delay, "standby", True)]  # the primary's alive token
        self.both: list[float] = []
        #: the standby's next withdrawal never reaches the primary (its session had not heard of the token)
        self.unheard = False

    def kill_primary(self, t: float) -> None:
        self.primary = None
        self.inbox.append((t + self.delay, "standby", False))

    def freeze_primary(self, t: float, lease: float) -> AnswerRule:
        """SIGSTOP: the primary's rule is not consulted and hears nothing; its token goes at the standby when
        its lease runs out. Returns the rule, for :meth:`resume_primary`."""
        frozen, self.primary = self.primary, None
        assert frozen is not None
        self.inbox.append((t + lease + self.delay, "standby", False))
        return frozen

    def resume_primary(self, rule: AnswerRule, t: float, lost: bool = False) -> None:
        """SIGCONT: the same rule goes on; the sessions reconnect, and the tokens there reach each other: the
        standby's running token, and its answering token unless ``lost`` (withdrawn before the primary's
        session asked for it)."""
        self.primary = rule
        self.inbox.append((t + self.delay, "standby", True))
        self.inbox.append((t + self.delay, "primary-running", True))
        if self.standby.last and not lost:
            self.inbox.append((t + self.delay, "primary", True))

    def start_primary(self, t: float, lost: bool = False) -> None:
        """A primary (re)starts: its token, its subscriber (the standby's tokens reach it from its session's
        history) and its query at once. ``lost``: the standby withdraws its answering token before the new
        primary's session has heard of it, so no event of that token reaches the primary: its query decides."""
        self.primary = AnswerRule(t, self.grace_s, self.away_s)
        # what was on its way to the old process is lost with it: the new one's session starts afresh
        self.inbox = [m for m in self.inbox if not m[1].startswith("primary")]
        self.inbox.append((t + self.delay, "standby", True))
        self.inbox.append((t + self.delay, "primary-running", True))
        self.inbox.append((t + self.delay, "standby-query", self.primary.asking()))
        if self.standby.last and lost:
            self.unheard = True
        elif self.standby.last:  # the standby's answering token is already there: it reaches the new primary
            self.inbox.append((t + self.delay, "primary", True))

    def _standby_changed(self, t: float) -> None:
        """The standby's answering token follows its answer, and reaches the primary ``delay`` later."""
        if self.unheard and not self.standby.last:
            self.unheard = False
            return
        self.inbox.append((t + self.delay, "primary", self.standby.last))

    def run(self, t0: float, t1: float) -> None:
        for step in range(round(t0 * 1000), round(t1 * 1000)):
            t = step / 1000
            for msg in [m for m in self.inbox if m[0] <= t]:
                self.inbox.remove(msg)
                _, to, present = msg
                if to == "standby":
                    before = self.standby.last
                    if self.standby.token(present, t) != before:
                        self._standby_changed(t)
                elif to == "standby-query":  # the standby's session answers with its tokens as they are now
                    self.inbox.append((t + self.delay, "primary-queried", (self.standby.last, present)))
                elif self.primary is None:
                    continue  # a frozen (or dead) primary hears nothing
                elif to == "primary-running":
                    self.primary.running(present, t)
                    if self.primary.reached:
                        self.inbox.append((t + self.delay, "standby-query", self.primary.asking()))
                elif to == "primary-queried":
                    answer, asked = present
                    self.primary.queried(answer, t, decides_absence=True, asked=asked)
                else:
                    self.primary.token(present, t)
            before = self.standby.last
            if self.standby.answering(t) != before:
                self._standby_changed(t)
            p = self.primary.answering(t) if self.primary is not None else False
            if p and self.standby.last:
                self.both.append(t)


@settings(max_examples=60)
@given(
    delay=st.floats(0.001, 0.2),
    kill=st.floats(1.5, 3.0),
    back=st.floats(0.05, 2.0),
    lost=st.booleans(),
)
def test_with_tokens_that_arrive_within_the_grace_one_answers_and_hand_back_never_doubles(delay, kill, back, lost):
    """``lost``: the standby's withdrawal races the returning primary's subscriber, which then hears nothing of
    that token; its query at once decides, though the standby's running token reaches it meanwhile."""
    # the timeline runs in 1 ms steps: a withdrawal arriving within a step of the primary's return is in either
    assume(abs(back - delay) > 0.002)
    pair = _Pair(grace_s=0.5, delay=delay)
    pair.run(0.0, kill)
    assert pair.primary is not None and pair.primary.last and not pair.standby.last  # the primary alone
    pair.kill_primary(kill)
    pair.run(kill, kill + back)
    assert pair.standby.last == (back > delay)  # the standby takes over once the token's withdrawal arrives
    pair.start_primary(kill + back, lost=lost)
    pair.run(kill + back, kill + back + 0.5 + 4 * delay + 0.01)
    assert pair.primary is not None and pair.primary.last and not pair.standby.last  # handed back
    # within a round trip of its return, not at its grace: the cars' gap is the standby's stop to this
    assert pair.primary.switches[-1][0] <= kill + back + 2 * delay + 0.003, pair.primary.switches
    assert pair.both == []  # never both, at start, at takeover or at hand-back


@settings(max_examples=60)
@given(
    delay=st.floats(0.001, 0.15),
    freeze=st.floats(1.0, 2.0),
    frozen=st.floats(1.01, 3.0),
    lost=st.booleans(),
)
def test_a_primary_back_from_a_freeze_never_answers_beside_the_standby(delay, freeze, frozen, lost):
    """Frozen longer than ``away_s`` (1 s here; its lease 0.5 s): the standby takes over, and the primary, back,
    relearns: never both, and the primary answers alone again once the standby has handed back, before its
    grace: the standby's running token tells it the sessions are back, and its query then finds what the standby
    does (``lost``: the standby's answering token never reaches it as an event, withdrawn first)."""
    pair = _Pair(grace_s=0.5, delay=delay, away_s=1.0)
    pair.run(0.0, freeze)
    assert pair.primary is not None and pair.primary.last and not pair.standby.last
    rule = pair.freeze_primary(freeze, lease=0.5)
    pair.run(freeze, freeze + frozen)
    assert pair.standby.last  # the lease ran out: the standby took over
    back = freeze + frozen
    pair.resume_primary(rule, back, lost=lost)
    pair.run(back, back + 0.5)
    assert pair.both == []
    assert rule.switches[-1][0] <= back + 3 * delay + 0.004  # a query's round trip after the reconnection, 1 ms steps
    assert pair.primary is not None and pair.primary.last and not pair.standby.last
    assert rule.away and rule.away[0][1] == pytest.approx(frozen, abs=0.002)


def test_a_split_makes_both_answer_and_healing_leaves_the_primary_alone():
    primary, standby = AnswerRule(0.0, 0.5), AnswerRule(0.0, 0.5)
    standby.token(True, 0.01)  # connected: the standby sees the primary's token
    assert primary.answering(0.5) and not standby.answering(0.5)
    assert standby.token(False, 1.0)  # the link between them breaks: the standby sees the token go ...
    assert primary.answering(1.0)  # ... and the primary, seeing no standby token, answers on: both answer
    assert not standby.token(True, 2.0)  # healed: the standby sees the primary again and stops
    assert not primary.token(True, 2.0)  # the primary saw the standby's token (declared in the split) ...
    assert primary.token(False, 2.01)  # ... which the standby withdrew on stopping: the primary alone
    assert not standby.answering(3.0)


# -- what zenoh-pair writes ------------------------------------------------------------------------------------
def test_pairing_with_a_standby_writes_both_servers_into_each_car_and_the_servers_mutual_rules(tmp_path, capsys):
    out = tmp_path / "fleet"
    argv = ["zenoh-pair", str(out), "--fleet", "--cars", "car1", "car2", "--server", "gpu1", "--standby", "gpu2"]
    assert main([*argv, "--server-host", "10.0.0.9", "--standby-host", "10.0.0.10", "--view", "base"]) == 0
    text = capsys.readouterr().out
    assert "standby gpu2" in text and "while gpu1 is not alive" in text
    for car in ("car1", "car2"):
        cfg = _json5(out / car / "car.json5")
        assert cfg["connect"]["endpoints"] == ["tls/10.0.0.9:7447", "tls/10.0.0.10:7447"]
        assert {"id": "pilot-host", "cert_common_names": ["gpu1", "gpu2"]} in cfg["access_control"]["subjects"]
    assert _json5(out / "base" / "base.json5")["connect"]["endpoints"][1] == "tls/10.0.0.10:7447"
    primary, standby = _json5(out / "server" / "server.json5"), _json5(out / "standby" / "server.json5")
    assert primary["connect"]["endpoints"] == ["tls/10.0.0.10:7447"]  # each dials the other
    assert standby["connect"]["endpoints"] == ["tls/10.0.0.9:7447"]
    for cfg, other, subject in ((primary, "gpu2", "pair-standby"), (standby, "gpu1", "pair-primary")):
        assert cfg["transport"]["link"]["tx"]["lease"] == 1000
        acl = cfg["access_control"]
        rules = {r["id"]: r for r in acl["rules"]}
        pair = rules["pair-liveliness"]
        assert pair["key_exprs"] == ["pilot-servers/gpu1/**"]  # the pair's tokens and nothing else
        assert set(pair["messages"]) <= {
            "liveliness_token",
            "declare_liveliness_subscriber",
            "liveliness_query",
            "reply",
        }
        assert {"id": subject, "cert_common_names": [other]} in acl["subjects"]
        # the other server is in no other policy: no car's data and no subscription passes between them
        other_subjects = {s["id"] for s in acl["subjects"] if other in s.get("cert_common_names", [])}
        assert other_subjects == {subject}
        assert [p for p in acl["policies"] if subject in p["subjects"]] == [
            {"rules": ["pair-liveliness"], "subjects": [subject]}
        ]
        assert not any("cert_common_names" not in s for s in acl["subjects"])  # no catch-all subject
    from asyncdonkey.parts.zenoh.link import zenoh_config

    assert role_from_config(zenoh_config(out / "server" / "server.json5")) == ServerRole("gpu1", standby="gpu2")
    assert role_from_config(zenoh_config(out / "standby" / "server.json5")) == ServerRole("gpu2", primary="gpu1")


def test_standby_options_are_checked(tmp_path, capsys):
    base = ["zenoh-pair", str(tmp_path / "a"), "--fleet", "--cars", "c1", "--server", "gpu1"]
    assert main([*base, "--standby", "gpu2"]) == 2  # both on localhost:7447
    assert "the server's own address" in capsys.readouterr().err
    assert main([*base, "--standby-host", "10.0.0.2"]) == 2
    assert "name it with --standby NAME" in capsys.readouterr().err
    assert main([*base, "--standby", "gpu1", "--standby-port", "7448"]) == 2
    assert "must differ" in capsys.readouterr().err
    from asyncdonkey.parts.zenoh.link import zenoh_config

    alone = zenoh_config(mode="router", listen=["tcp/127.0.0.1:7447"])
    with pytest.raises(StandbyConfigError, match=r"dials no other session.*--connect"):
        role_for(alone, name="gpu2", standby_of="gpu1")
    with pytest.raises(StandbyConfigError, match="needs a name"):
        role_for(alone, standby="gpu2")
    assert role_for(alone) is None
    err_argv = ["pilot-server", str(MODELS / "sim_pilot.onnx"), "--cars", "c1", "--listen", "tcp/127.0.0.1:0"]
    assert main([*err_argv, "--mode", "router", "--standby-of", "gpu1", "--name", "gpu2"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "asyncdonkey pilot-server: error: standby 'gpu2'" in err


# -- the car: two answers for one frame ------------------------------------------------------------------------
@pytest.mark.realtime
@pytest.mark.network
def test_a_second_senders_answer_to_the_same_frame_is_counted_and_never_makes_the_command_younger():
    from asyncdonkey.parts.zenoh import PILOT_COMMAND, ZenohLink, ZenohPublisher, ZenohSubscriber

    from ..waiting import wait_until
    from .zenoh_loopback import connector, free_port, listener

    port = free_port()
    car = ZenohLink("cars/car1", listener(port), insecure=True)
    a, b = ZenohLink("cars/car1", connector(port)), ZenohLink("cars/car1", connector(port))
    cmd = ["pilot/angle", "pilot/throttle"]
    try:
        sub = ZenohSubscriber(car, cmd, group=PILOT_COMMAND, ping_every_s=0)
        server_a, server_b = (ZenohPublisher(x, cmd, group=PILOT_COMMAND) for x in (a, b))
        time.sleep(0.3)
        for _ in range(4):  # both servers' numberings confirmed (the car takes a sender from its second sample)
            server_a.run(0.1, 0.5, 0.0, 0.0)
            server_b.run(0.2, 0.5, 0.0, 0.0)
            time.sleep(0.05)
        wait_until(lambda: sub.received >= 3, 5)
        taken = sub.received
        frame_at = time.monotonic() - 0.040  # a new frame, 40 ms old when both answers leave
        server_a.run(0.3, 0.6, 0.040, 0.040)
        wait_until(lambda: sub.received == taken + 1, 5)
        sub.run()
        first = sub.output_origin()
        assert first is not None and abs(first - frame_at) < 0.010  # the frame's own age, within a few ms
        dups = sub.duplicates
        age_b = time.monotonic() - frame_at  # the same frame, answered later by the other server
        server_b.run(0.9, 0.9, age_b, age_b)
        wait_until(lambda: sub.duplicates == dups + 1, 5)
        assert sub.run() == (0.3, 0.6)  # the first answer kept
        assert sub.output_origin() == first  # and its origin: the second answer made nothing younger
        server_b.run(0.4, 0.7, 0.0, 0.0)  # the other server's answer to a newer frame is taken
        wait_until(lambda: sub.run() == (0.4, 0.7), 5)
        assert sub.counters()["duplicates"] == sub.duplicates >= 1
    finally:
        for link in (car, a, b):
            link.close()


class _Constant:
    """A model of the pilot's frame size that answers every frame with ``(angle, 0.5)``."""

    pilot = types.SimpleNamespace(image_shape=(120, 160, 3))

    def __init__(self, angle: float) -> None:
        self.angle = angle

    def infer(self, frames):
        return [(self.angle, 0.5)] * len(frames)


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.asyncio
async def test_a_split_makes_both_servers_answer_and_the_car_keeps_the_first_answer_of_each_frame(tmp_path):
    """The servers cannot see each other (each dials a port where nothing listens): both answer every frame;
    the car takes one answer per frame and counts the other, and its command's age is its frame's."""
    from asyncdonkey.parts.zenoh import PILOT_COMMAND, PilotServer, ZenohLink, ZenohPublisher, ZenohSubscriber
    from asyncdonkey.parts.zenoh.link import zenoh_config

    from ..waiting import await_until
    from .standby_fleet import pair_standby_fleet
    from .zenoh_loopback import free_port

    files = pair_standby_fleet(tmp_path / "fleet", ["car1"])
    configs = []
    for path in (files.server_config, files.standby_config):
        cfg = zenoh_config(path)
        cfg.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{free_port()}"]))  # nobody there
        configs.append(cfg)
    primary = PilotServer(_Constant(0.1), ["car1"], config=configs[0], grace_s=0.3)
    standby = PilotServer(_Constant(0.1), ["car1"], config=configs[1], grace_s=0.3)
    serving = [asyncio.ensure_future(s.serve()) for s in (primary, standby)]
    car = ZenohLink("cars/car1", files.car_configs["car1"])
    try:
        cam = ZenohPublisher(car, ["cam/image_array"])
        sub = ZenohSubscriber(car, ["pilot/angle", "pilot/throttle"], group=PILOT_COMMAND, ping_every_s=0)
        ages: list[float] = []
        sub.subscribe(lambda value, origin: ages.append(car.now() - origin))
        await await_until(lambda: primary.answering and standby.answering, timeout=5)  # each believes it alone
        frame = np.zeros((120, 160, 3), np.uint8)
        for _ in range(5):  # both subscriptions reach the car, both servers' numberings are confirmed there
            cam.run(frame, 0.0)
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.2)
        start = dict(sub.counters())
        for _ in range(30):
            cam.run(frame, 0.0)
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.2)
        c = sub.counters()
        taken, dup = c["received"] - start["received"], c["duplicates"] - start["duplicates"]
        answered = sum(s.counters()["car1"]["answered"] for s in (primary, standby))
        assert primary.counters()["car1"]["answered"] >= 20 and standby.counters()["car1"]["answered"] >= 20
        # a frame's first answer is taken and the other server's counted: one command per frame on a quiet
        # machine (30 of 30). Two answers to one frame are told apart by their origins (within same_frame_s), which
        # include each path's unmeasured transit: under load a second answer can land as a newer frame (31 of 30
        # once in a loaded CI run, with a warm-up frame's answer landing late), so a little slack
        assert 25 <= taken <= 33, c
        assert dup >= 20 and taken + dup <= answered, (c, answered)  # the second answers: counted, not taken
        # each command as old as its frame: a few ms on loopback, within the failsafe window on a loaded machine
        assert min(ages) >= 0 and max(ages[-25:]) < 0.25, ages
    finally:
        for s in (primary, standby):
            s.stop()
        await asyncio.gather(*serving)
        car.close()
        for s in (primary, standby):
            s.close()


# -- the fleet as processes: takeover and hand-back -----------------------------------------------------------
@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    from .fleet_car import record_sim_frames

    path = tmp_path_factory.mktemp("frames") / "frames.npy"
    record_sim_frames(str(path), count=12)
    return path


def _decisions(*servers: Any) -> list[str]:
    """Each server's lines about answering, for a failure's message."""
    return [line.strip()[-150:] for p in servers for line in p.lines if "pilot server" in line]


def _gaps(arrivals: list[float], t0: float, t1: float) -> tuple[float, float]:
    """The longest time without a command between t0 and t1 (arrival times, monotonic clock), and when it began."""
    ts = [t0, *[t for t in arrivals if t0 < t < t1], t1]
    return max((b - a, a) for a, b in itertools.pairwise(ts))


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.subprocess
def test_kill_9_of_the_primary_the_standby_takes_over_and_hands_back_without_double_answers(tmp_path, frames):
    from ..waiting import wait_until
    from .standby_fleet import StandbyFleet

    cars = ["car1", "car2", "car3", "car4"]
    fleet = StandbyFleet(tmp_path / "fleet", cars)
    primary, standby = fleet.server(fleet.files.server_config), fleet.server(fleet.files.standby_config)
    procs = fleet.car_processes(frames)
    everyone = [*procs, standby]
    try:
        wait_until(lambda: all(p.of("driving") for p in procs), 45, lambda: "every car to drive", 0.05)
        t_all = max(p.of("driving")[0]["t"] for p in procs)
        time.sleep(2.0)
        t_kill = time.monotonic()
        primary.p.send_signal(signal.SIGKILL)
        primary.stop()
        time.sleep(2.0)
        t_back = time.monotonic()
        primary = fleet.server(fleet.files.server_config)  # the primary returns: the standby hands back
        everyone.append(primary)
        wait_until(lambda: any("'gpu1': answering the cars" in line for line in primary.lines), 20, "hand-back")
        time.sleep(2.0)
        t_end = time.monotonic()
    finally:
        for p in procs:
            p.stop()
        for p in (primary, standby):
            p.stop()
    reports = {r["car"]: r for p in procs for r in p.of("report")}
    assert set(reports) == set(cars), [p.lines[-3:] for p in procs]
    standby_log = "".join(standby.lines)
    assert "'gpu2': answering the cars ('gpu1' is not alive)" in standby_log, standby_log[-2000:]
    assert "'gpu2': stopped answering" in standby_log, standby_log[-2000:]
    for car, r in reports.items():
        arrivals = r["arrivals"]
        # commanded throughout: the standby takes over after the kill and hands back to the returning primary
        # with no long silence. The goal, a gap below the failsafe window (250 ms) so that no car stops, is a
        # figure of benchmarks/fleet_failover.py (55-120 ms at the kill, 56-102 ms at the hand-back here); six
        # processes on a loaded 2-core machine guarantee less. This bound separates a takeover from none (the gap
        # would run from the kill to the primary's return, over 2 s) and a hand-back from one that waits out the
        # 1 s grace (a missed withdrawal: 1.04-1.10 s)
        gap, at = _gaps(arrivals, t_all + 0.2, t_end)
        assert gap < 0.9, (car, gap, "from kill", at - t_kill, "from return", at - t_back)
        # never two answers for one frame: not while the primary alone answered, not at takeover, not at hand-back
        assert r["counters"]["duplicates"] == 0, (car, r["counters"], _decisions(primary, standby))
        lat = r["latency_ms"]
        assert lat and max(lat) < 4 * FAILSAFE_S * 1e3, (car, max(lat))  # each command aged by its own frame
        assert any(t_kill < t < t_back for t in arrivals) and any(t > t_back + 1.5 for t in arrivals)


@pytest.mark.realtime
@pytest.mark.network
@pytest.mark.subprocess
def test_a_frozen_primary_stops_the_cars_by_their_failsafe_until_the_standby_drives_them(tmp_path, frames):
    """SIGSTOP keeps the primary's sockets open: the standby knows only when the primary's 1 s lease runs out,
    so each car's own failsafe stops it first; then the standby drives. On SIGCONT the primary, away longer than
    its ``away_s``, relearns its pair before it answers: it never answers beside the standby, and takes the cars
    back. Every command a car stores is aged by its own frame throughout."""
    from ..waiting import wait_until
    from .standby_fleet import StandbyFleet

    cars = ["car1", "car2"]
    fleet = StandbyFleet(tmp_path / "fleet", cars)
    primary, standby = fleet.server(fleet.files.server_config), fleet.server(fleet.files.standby_config)
    procs = fleet.car_processes(frames)
    try:
        wait_until(lambda: all(p.of("driving") for p in procs), 45, lambda: "every car to drive", 0.05)
        time.sleep(1.5)
        t_freeze = time.monotonic()
        primary.p.send_signal(signal.SIGSTOP)
        wait_until(lambda: "'gpu2': answering the cars" in "".join(standby.lines), 20, "the standby to take over")
        time.sleep(2.0)  # driven by the standby; the primary frozen past its away_s (2 s)
        t_resume = time.monotonic()
        primary.p.send_signal(signal.SIGCONT)
        wait_until(lambda: "'gpu2': stopped answering" in "".join(standby.lines), 20, "the hand-back")
        time.sleep(1.5)
        t_end = time.monotonic()
    finally:
        primary.p.send_signal(signal.SIGCONT)  # a frozen process would not hear SIGTERM
        for p in (*procs, primary, standby):
            p.stop()
    reports = {r["car"]: r for p in procs for r in p.of("report")}
    assert set(reports) == set(cars), [p.lines[-3:] for p in procs]
    for car, r in reports.items():
        arrivals, changes = r["arrivals"], r["throttle_changes"]
        # nobody commands the car until the lease runs out: its own failsafe stops it meanwhile
        assert any(v == 0.0 and t_freeze < t < t_resume for t, v in changes), (car, changes)
        # the standby drives it during the freeze, and the primary after its return
        assert any(t_freeze + 0.3 < t < t_resume for t in arrivals), (car, "no command from the standby")
        assert any(t > t_end - 1.0 for t in arrivals), (car, "no command after the hand-back")
        # back, the primary answered nothing beside the standby: no frame answered twice
        assert r["counters"]["duplicates"] == 0, (car, r["counters"], _decisions(primary, standby))
        # every stored command is aged by its own frame, as in the kill test
        lat = r["latency_ms"]
        assert lat and max(lat) < 4 * FAILSAFE_S * 1e3, (car, max(lat))
    primary_log = "".join(primary.lines)
    assert "'gpu1': its loop was away" in primary_log, primary_log[-2000:]
