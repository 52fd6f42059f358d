"""The virtual receiver as a configurable u-blox receiver on a real pty: silent until
configured, then exactly the messages it was asked for, on its own port, at the rate asked,
with GEOs only when their use is on; a signal configuration restarts its tracking."""

from __future__ import annotations

import contextlib
import itertools

from drivers.ubx_setup import configure_device
from service.core.errors import ReceiverRefusedError
from service.core.receiver_setup import ReceiverSetup
from tests.support.receiver import ACK_WAIT_S, rawx_svs, read_stream, receiver_thread, wait_for

GEOS = {1, 2, 3, 4, 5}
ACK_FRAME_BYTES = 10  # sync 2, class/id 2, length 2, payload 2, checksum 2


def test_silent_until_configured_then_only_what_was_asked():
    with receiver_thread() as rx:
        stats = rx.receiver.stats
        wait_for(lambda: stats.epochs_made >= 5, "5 epochs of the fresh receiver")
        assert stats.bytes_written == 0 and stats.restarts == 0
        configure_device(rx.device, 115200, ReceiverSetup(model="f9", timeout_s=ACK_WAIT_S))
        assert stats.restarts == 1  # the signal configuration restarted tracking
        frames = read_stream(rx.device, 20)
    assert all(raw[:2] == b"\xb5\x62" for raw, _ in frames)  # UBX only: no NMEA, no RTCM
    names = {m.identity for _, m in frames}
    assert names == {"RXM-RAWX", "RXM-MEASX", "RXM-SFRBX"}
    rawx = [m for _, m in frames if m.identity == "RXM-RAWX"]
    assert any(GEOS & {sv for sv, ok in rawx_svs(m).items() if ok} for m in rawx)
    sfrbx = [m for _, m in frames if m.identity == "RXM-SFRBX"]
    assert any(m.gnssId == 3 and m.svId in GEOS for m in sfrbx)


def test_the_rate_asked_for():
    with receiver_thread() as rx:
        configure_device(rx.device, 115200, ReceiverSetup(rate_hz=5.0, timeout_s=ACK_WAIT_S))
        frames = read_stream(rx.device, 8)
    tows = [round(m.rcvTow * 1000) for _, m in frames if m.identity == "RXM-RAWX"]
    assert {b - a for a, b in itertools.pairwise(tows)} == {200}


def test_no_geos_while_their_use_is_refused():
    with receiver_thread(nak=["CFG_BDS_USE_GEO_PRN"]) as rx:
        with contextlib.suppress(ReceiverRefusedError):
            configure_device(rx.device, 115200, ReceiverSetup(timeout_s=ACK_WAIT_S))
        frames = read_stream(rx.device, 30)  # 3 s: every GEO would have a D2 subframe
    rawx = [m for _, m in frames if m.identity == "RXM-RAWX"]
    seen = set().union(*(rawx_svs(m) for m in rawx))
    assert seen and not seen & GEOS
    assert not any(m.svId in GEOS for _, m in frames if m.identity == "RXM-SFRBX")


def test_output_asked_on_another_port_is_not_sent_here():
    with receiver_thread(port="uart1") as rx:
        stats = rx.receiver.stats
        configure_device(rx.device, 115200, ReceiverSetup(port="usb", timeout_s=ACK_WAIT_S))
        made = stats.epochs_made
        wait_for(lambda: stats.epochs_made >= made + 5, "5 more epochs")
        assert rx.responder.outputs == set()
        assert stats.bytes_written == ACK_FRAME_BYTES * stats.answered == 6 * ACK_FRAME_BYTES
