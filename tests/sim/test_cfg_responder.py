"""The virtual receiver's CFG interface: what it acknowledges, refuses and applies, on
messages built here with pyubx2 and answers read back with pyubx2."""

from __future__ import annotations

import pytest
from pyubx2 import GET, POLL, SET, UBXMessage, UBXReader

from service.sim.cfg import CfgResponder


def _answer(responder: CfgResponder, msg: UBXMessage) -> tuple[str, int, int] | None:
    """(ACK-ACK|ACK-NAK, class, id) of the responder's answer, None if it said nothing."""
    raw = responder.handle(UBXReader.parse(msg.serialize(), msgmode=3))  # SETPOLL: as read
    if not raw:
        return None
    ack = UBXReader.parse(raw, msgmode=GET)
    return ack.identity, ack.clsID, ack.msgID


def _valset(*keys: tuple[str, object], layers: int = 1) -> UBXMessage:
    return UBXMessage.config_set(layers, 0, list(keys))


def test_a_fresh_receiver_sends_nothing_and_does_not_use_geos():
    r = CfgResponder()
    assert r.outputs == set() and r.use_geo is False and r.bds_on is True


def test_valset_keys_are_acknowledged_and_applied_on_the_own_port_only():
    r = CfgResponder(port="uart1")
    assert _answer(r, _valset(("CFG_BDS_USE_GEO_PRN", 1))) == ("ACK-ACK", 0x06, 0x8A)
    assert r.use_geo is True
    for name in ("RAWX", "MEASX", "SFRBX"):
        assert _answer(r, _valset((f"CFG_MSGOUT_UBX_RXM_{name}_USB", 1)))[0] == "ACK-ACK"
    assert r.outputs == set()  # another port: acknowledged, nothing sent here
    for name in ("RAWX", "MEASX", "SFRBX"):
        assert _answer(r, _valset((f"CFG_MSGOUT_UBX_RXM_{name}_UART1", 1)))[0] == "ACK-ACK"
    assert r.outputs == {"RXM-RAWX", "RXM-MEASX", "RXM-SFRBX"}
    assert _answer(r, _valset(("CFG_MSGOUT_UBX_RXM_MEASX_UART1", 0)))[0] == "ACK-ACK"
    assert r.outputs == {"RXM-RAWX", "RXM-SFRBX"}


def test_a_signal_configuration_restarts_tracking():
    r = CfgResponder()
    msg = _valset(("CFG_SIGNAL_BDS_ENA", 1), ("CFG_SIGNAL_BDS_B1_ENA", 1))
    assert _answer(r, msg)[0] == "ACK-ACK"
    assert r.restart is True and r.bds_on is True
    r.restart = False
    assert _answer(r, _valset(("CFG_SIGNAL_BDS_B1_ENA", 0)))[0] == "ACK-ACK"
    assert r.restart is True and r.bds_on is False


def test_valset_is_atomic_and_unsupported_keys_are_refused():
    r = CfgResponder()
    # GPS is not simulated: the whole message is refused, the GEO key with it
    msg = _valset(("CFG_BDS_USE_GEO_PRN", 1), ("CFG_SIGNAL_GPS_ENA", 1))
    assert _answer(r, msg) == ("ACK-NAK", 0x06, 0x8A)
    assert r.use_geo is False
    assert _answer(r, _valset((0x10990001, b"\x03")))[0] == "ACK-NAK"  # a key pyubx2 lacks


@pytest.mark.parametrize(
    ("meas_ms", "nav", "answer", "period"),
    [
        (100, 1, "ACK-ACK", 100),
        (200, 1, "ACK-ACK", 200),
        (1000, 1, "ACK-ACK", 1000),
        (50, 1, "ACK-NAK", 100),
        (150, 1, "ACK-NAK", 100),
        (200, 2, "ACK-NAK", 100),
    ],
)
def test_rates_are_whole_multiples_of_the_simulators_period(meas_ms, nav, answer, period):
    for msg in (
        _valset(("CFG_RATE_MEAS", meas_ms), ("CFG_RATE_NAV", nav)),
        UBXMessage("CFG", "CFG-RATE", SET, measRate=meas_ms, navRate=nav, timeRef=1),
    ):
        r = CfgResponder(base_period_ms=100)
        assert _answer(r, msg)[0] == answer
        assert r.meas_period_ms == period


def test_named_keys_and_messages_are_refused_on_request():
    r = CfgResponder(nak=["CFG_BDS_USE_GEO_PRN", "CFG-CFG"])
    assert _answer(r, _valset(("CFG_BDS_USE_GEO_PRN", 1)))[0] == "ACK-NAK"
    assert r.use_geo is False
    assert _answer(r, _valset(("CFG_RATE_MEAS", 100)))[0] == "ACK-ACK"
    save = UBXMessage(
        "CFG",
        "CFG-CFG",
        SET,
        clearMask=b"\0\0\0\0",
        saveMask=b"\x1f\x1f\0\0",
        loadMask=b"\0\0\0\0",
        devBBR=1,
    )
    assert _answer(r, save)[0] == "ACK-NAK"
    with pytest.raises(ValueError, match="unknown configuration key"):
        CfgResponder(nak=["CFG_NO_SUCH_KEY"])


def test_m8_messages():
    r = CfgResponder(port="usb")
    blocks = {"gnssId_01": 0, "enable_01": 1, "gnssId_02": 3, "enable_02": 1}
    gnss = UBXMessage(
        "CFG",
        "CFG-GNSS",
        SET,
        msgVer=0,
        numTrkChHw=0,
        numTrkChUse=255,
        numConfigBlocks=2,
        resTrkCh_01=8,
        maxTrkCh_01=16,
        sigCfMask_01=1,
        resTrkCh_02=8,
        maxTrkCh_02=16,
        sigCfMask_02=1,
        **blocks,
    )
    assert _answer(r, gnss) == ("ACK-ACK", 0x06, 0x3E)
    assert r.bds_on and r.use_geo and r.restart  # an M8 tracks the GEOs with BeiDou
    rawx = UBXMessage("CFG", "CFG-MSG", SET, msgClass=0x02, msgID=0x15, rateUSB=1)
    assert _answer(r, rawx) == ("ACK-ACK", 0x06, 0x01)
    assert r.outputs == {"RXM-RAWX"}
    pvt = UBXMessage("CFG", "CFG-MSG", SET, msgClass=0x01, msgID=0x07, rateUSB=1)
    assert _answer(r, pvt)[0] == "ACK-NAK"  # NAV-PVT: not something this receiver makes
    prt = UBXMessage("CFG", "CFG-PRT", SET, portID=1, baudRate=9600)
    assert _answer(r, prt)[0] == "ACK-NAK"


def test_polls_and_a_silent_receiver_get_no_answer():
    assert _answer(CfgResponder(), UBXMessage("CFG", "CFG-RATE", POLL)) is None
    silent = CfgResponder(silent=True)
    assert _answer(silent, _valset(("CFG_BDS_USE_GEO_PRN", 1))) is None
    assert silent.use_geo is False
