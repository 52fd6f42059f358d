"""Receiver set-up for u-blox (drivers/ubx_setup.py): the messages, read back with pyubx2
against values written out here, and the ACK/NAK exchange through a real pty with the
virtual receiver answering on the other end."""

from __future__ import annotations

import pytest
from pyubx2 import SET, UBXReader

from drivers.ubx_setup import configure_device, save_step, setup_steps
from service.core.errors import InputError, ReceiverRefusedError, ReceiverSilentError
from service.core.receiver_setup import ReceiverSetup
from tests.support.receiver import ACK_WAIT_S, receiver_thread


def _parsed(step):
    return UBXReader.parse(step.raw, msgmode=SET)


def _keys(msg) -> dict[str, object]:
    return {k: v for k, v in vars(msg).items() if k.startswith("CFG_")}


def test_f9_valset_keys_one_message_each_signals_together():
    steps = setup_steps(ReceiverSetup(model="f9", rate_hz=10.0), "uart1")
    msgs = [_parsed(s) for s in steps]
    assert all(m.identity == "CFG-VALSET" and (m.ram, m.bbr, m.flash) == (1, 0, 0) for m in msgs)
    assert [_keys(m) for m in msgs] == [
        {"CFG_SIGNAL_BDS_ENA": 1, "CFG_SIGNAL_BDS_B1_ENA": 1},
        {"CFG_BDS_USE_GEO_PRN": 1},
        {"CFG_RATE_MEAS": 100, "CFG_RATE_NAV": 1},
        {"CFG_MSGOUT_UBX_RXM_RAWX_UART1": 1},
        {"CFG_MSGOUT_UBX_RXM_MEASX_UART1": 1},
        {"CFG_MSGOUT_UBX_RXM_SFRBX_UART1": 1},
    ]
    # X20 takes the same keys
    assert [s.raw for s in setup_steps(ReceiverSetup(model="x20"), "uart1")] == [
        s.raw for s in steps
    ]


@pytest.mark.parametrize(
    ("device", "port", "suffix"),
    [
        ("/dev/ttyACM0", "auto", "USB"),
        ("/dev/ttyUSB0", "auto", "UART1"),
        ("/dev/pts/3", "auto", "UART1"),
        ("/dev/ttyACM0", "uart2", "UART2"),
    ],
)
def test_the_port_in_use(device, port, suffix):
    setup = ReceiverSetup(port=port, rate_hz=4.0)
    msgs = [_parsed(s) for s in setup_steps(setup, setup.port_for(device))]
    outs = {k for m in msgs for k in _keys(m) if k.startswith("CFG_MSGOUT")}
    assert outs == {f"CFG_MSGOUT_UBX_RXM_{n}_{suffix}" for n in ("RAWX", "MEASX", "SFRBX")}
    assert _keys(msgs[2])["CFG_RATE_MEAS"] == 250


def test_m8_gnss_rate_and_messages_on_the_port_only():
    steps = setup_steps(ReceiverSetup(model="m8", rate_hz=5.0), "usb")
    gnss, rate, *outs = (_parsed(s) for s in steps)
    assert gnss.identity == "CFG-GNSS"
    enabled = {
        getattr(gnss, f"gnssId_{i:02d}"): getattr(gnss, f"enable_{i:02d}")
        for i in range(1, gnss.numConfigBlocks + 1)
    }
    assert enabled[3] == 1 and enabled[0] == 1  # BeiDou and GPS on
    assert enabled[6] == 0  # GLONASS off: an M8 tracks at most three GNSS
    b1i = [getattr(gnss, f"sigCfMask_{i:02d}") for i in range(1, 8) if enabled.get(3)]
    assert set(b1i) == {1}
    assert (rate.identity, rate.measRate, rate.navRate) == ("CFG-RATE", 200, 1)
    assert [(m.identity, m.msgClass, m.msgID) for m in outs] == [
        ("CFG-MSG", 0x02, 0x15),
        ("CFG-MSG", 0x02, 0x14),
        ("CFG-MSG", 0x02, 0x13),
    ]
    for m in outs:
        assert (m.rateUSB, m.rateUART1, m.rateUART2, m.rateSPI, m.rateDDC) == (1, 0, 0, 0, 0)


def test_save_messages():
    f9 = ReceiverSetup(model="f9")
    steps = setup_steps(f9, "uart1")
    save = _parsed(save_step(f9, steps))
    assert save.identity == "CFG-VALSET" and (save.ram, save.bbr, save.flash) == (0, 1, 1)
    assert _keys(save) == {k: v for s in steps for k, v in _keys(_parsed(s)).items()}
    m8 = ReceiverSetup(model="m8")
    cfg = _parsed(save_step(m8, setup_steps(m8, "uart1")))
    assert cfg.identity == "CFG-CFG" and cfg.devFlash == 1 and cfg.devBBR == 1
    assert cfg.saveMask == b"\x1f\x1f\x00\x00" and cfg.clearMask == b"\x00" * 4


@pytest.mark.parametrize("model", ["f9", "m8"])
def test_every_message_acknowledged_and_in_effect(model):
    with receiver_thread(port="uart1") as rx:
        setup = ReceiverSetup(model=model, rate_hz=5.0, timeout_s=ACK_WAIT_S)
        result = configure_device(rx.device, 115200, setup)
        assert [s.what for s in result.acked] == [
            s.what for s in setup_steps(ReceiverSetup(model=model, rate_hz=5.0), "uart1")
        ]
        assert not result.refused and not result.saved
        r = rx.responder
        assert r.outputs == {"RXM-RAWX", "RXM-MEASX", "RXM-SFRBX"}
        assert r.use_geo and r.bds_on and r.meas_period_ms == 200
        assert all(ok for _, ok in r.answered)


def test_saved_only_after_every_ack():
    with receiver_thread() as rx:
        result = configure_device(rx.device, 115200, ReceiverSetup(timeout_s=ACK_WAIT_S), save=True)
        assert result.saved
        assert rx.responder.answered[-1] == ("CFG-VALSET", True)
        assert len(rx.responder.answered) == 7
    with receiver_thread(nak=["CFG_BDS_USE_GEO_PRN"]) as rx:
        with pytest.raises(ReceiverRefusedError) as exc:
            configure_device(rx.device, 115200, ReceiverSetup(timeout_s=ACK_WAIT_S), save=True)
        assert len(rx.responder.answered) == 6  # the save was never sent
        assert "nothing saved" in str(exc.value)


def test_a_refused_key_is_named_and_the_rest_is_still_set():
    with receiver_thread(nak=["CFG_BDS_USE_GEO_PRN"]) as rx:
        with pytest.raises(ReceiverRefusedError) as exc:
            configure_device(rx.device, 115200, ReceiverSetup(timeout_s=ACK_WAIT_S))
        text = str(exc.value)
        assert "refused (ACK-NAK) CFG-VALSET CFG_BDS_USE_GEO_PRN=1 (RAM);" in text
        assert "the other 5 messages were acknowledged" in text and "\n" not in text
        assert exc.value.exit_code == 5
        assert rx.responder.outputs == {"RXM-RAWX", "RXM-MEASX", "RXM-SFRBX"}
        assert rx.responder.use_geo is False


def test_a_receiver_that_never_answers():
    with receiver_thread(silent=True) as rx:
        with pytest.raises(ReceiverSilentError) as exc:
            configure_device(rx.device, 115200, ReceiverSetup(timeout_s=0.2))
        text = str(exc.value)
        assert "no answer (ACK/NAK) to CFG-VALSET CFG_SIGNAL_BDS_ENA=1" in text
        assert "sent twice" in text and "nothing was acknowledged" in text
        assert exc.value.exit_code == 3
        assert rx.responder.outputs == set()


def test_a_device_that_cannot_be_opened(tmp_path):
    with pytest.raises(InputError, match="cannot open"):
        configure_device(str(tmp_path / "ttyNONE"), 115200, ReceiverSetup(timeout_s=ACK_WAIT_S))
