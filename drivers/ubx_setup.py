"""Receiver set-up for u-blox: the CFG messages that make a receiver output what the fast
fix needs, and the ACK/NAK exchange that sends them.

What is asked (u-blox M8 Receiver Description / Protocol Specification 32.10.x; ZED-F9P and
X20 Interface Descriptions, "Configuration interface"):

- **M8** (``m8``): CFG-GNSS with GPS (+QZSS) and BeiDou B1I on (SBAS, Galileo, IMES,
  GLONASS off; an M8 tracks at most three GNSS at once and GEOs with BeiDou), CFG-RATE
  (measurement period, one navigation solution per measurement, GPS time reference), and
  CFG-MSG RXM-RAWX, RXM-MEASX, RXM-SFRBX at rate 1 on the port in use (0 on the others).
- **F9 / X20** (``f9``, ``x20``: the same keys): CFG-VALSET to the RAM layer of
  ``CFG-SIGNAL-BDS_ENA`` and ``CFG-SIGNAL-BDS_B1_ENA`` (one message: a GNSS enabled with no
  signal is an invalid configuration the receiver would refuse), ``CFG-BDS-USE_GEO_PRN``,
  ``CFG-RATE-MEAS`` with ``CFG-RATE-NAV`` = 1, and ``CFG-MSGOUT-UBX_RXM_{RAWX,MEASX,SFRBX}_<PORT>``
  = 1.

Every message is built with pyubx2's generators (``UBXMessage(..., SET, ...)``,
``UBXMessage.config_set``) and sent alone; the receiver answers each with UBX-ACK-ACK or
UBX-ACK-NAK naming its class and id. A message not answered within ``timeout_s`` is sent
once more; still no answer stops the set-up
(:class:`~service.core.errors.ReceiverSilentError`, exit 3). A NAK does not stop it: the
other messages are still sent, so that one run reports everything refused, and then
:class:`~service.core.errors.ReceiverRefusedError` (exit 5) names what was refused and what
is in effect. Only when every message was acknowledged is the configuration saved (``save``:
CFG-CFG on an M8, a CFG-VALSET of the same keys to the BBR and flash layers on F9/X20); the
set-up is never written to non-volatile memory half done.

The wait for an answer is a deadline whatever the device sends: it reads the bytes the port
has (at most ``_READ_TIMEOUT_S`` per read) and feeds them to the stream framer
(:class:`drivers.framing.Framer`, UBX only, payloads of at most an ACK's 2 bytes), checking
the deadline after every read. pyubx2's ``UBXReader.read`` is not used here: it returns only
on a whole message or a read that times out (50 ms of silence), so a device streaming NMEA
or garbage, or a UBX header claiming 65,535 bytes followed by a trickle, held the set-up for
as long as it talked.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import serial
from pyubx2 import SET, UBXMessage

from drivers.framing import Framer
from drivers.protocols import PROTOCOLS
from service.core.errors import ConfigError, InputError, ReceiverRefusedError, ReceiverSilentError
from service.core.receiver_setup import ReceiverSetup

log = logging.getLogger(__name__)

LAYER_RAM, LAYER_BBR, LAYER_FLASH = 1, 2, 4
"""CFG-VALSET layers (F9 Interface Description, UBX-CFG-VALSET)."""

_ACK_CLASS, _ACK_ID, _NAK_ID = 0x05, 0x01, 0x00
_ACK_PAYLOAD = 2  # UBX-ACK-ACK / ACK-NAK: the class and id of the message answered
_READ_TIMEOUT_S = 0.05  # one serial read; the ACK wait loops over these until its deadline
_READ_MAX = 4096  # bytes taken per read at most

_VALSET_PORT = {"uart1": "UART1", "uart2": "UART2", "usb": "USB", "spi": "SPI", "i2c": "I2C"}
_CFG_MSG_PORT = {
    "uart1": "rateUART1",
    "uart2": "rateUART2",
    "usb": "rateUSB",
    "spi": "rateSPI",
    "i2c": "rateDDC",
}
MEASUREMENT_MESSAGES = (
    ("RXM-RAWX", 0x02, 0x15),
    ("RXM-MEASX", 0x02, 0x14),
    ("RXM-SFRBX", 0x02, 0x13),
)
"""The UBX messages the fast fix reads: (name, class, id)."""

# CFG-GNSS blocks of an M8 (gnssId, resTrkCh, maxTrkCh, enable): GPS, SBAS, Galileo,
# BeiDou, IMES, QZSS, GLONASS; signal mask 0x01 (L1C/A, E1, B1I, L1C/A, L1) for each.
_M8_GNSS_BLOCKS = (
    (0, 8, 16, 1),
    (1, 1, 3, 0),
    (2, 4, 8, 0),
    (3, 8, 16, 1),
    (4, 0, 8, 0),
    (5, 0, 3, 1),
    (6, 8, 14, 0),
)


@dataclass(frozen=True, slots=True)
class CfgStep:
    """One configuration message: what it asks (for people) and its UBX frame."""

    what: str
    raw: bytes
    keys: tuple[tuple[str, int], ...] = ()  # CFG-VALSET: its (key, value) pairs

    @property
    def ids(self) -> tuple[int, int]:
        """(class, id) of the message, as an ACK names them."""
        return self.raw[2], self.raw[3]


def _valset(keys: Sequence[tuple[str, int]], layers: int = LAYER_RAM) -> CfgStep:
    msg = UBXMessage.config_set(layers, 0, list(keys))
    where = "RAM" if layers == LAYER_RAM else "BBR+flash"
    text = ", ".join(f"{k}={v}" for k, v in keys)
    return CfgStep(f"CFG-VALSET {text} ({where})", bytes(msg.serialize()), tuple(keys))


def setup_steps(setup: ReceiverSetup, port: str) -> list[CfgStep]:
    """The CFG messages that set ``setup`` up on a receiver, its measurements on ``port``
    (``uart1`` ... as in :data:`service.core.receiver_setup.PORTS`, not ``auto``)."""
    if port not in _VALSET_PORT:
        raise ConfigError(f"receiver port {port!r}: expected one of {', '.join(_VALSET_PORT)}")
    period_ms = setup.meas_period_ms
    if setup.model == "m8":
        kw: dict[str, Any] = {
            "msgVer": 0,
            "numTrkChHw": 0,
            "numTrkChUse": 0xFF,
            "numConfigBlocks": len(_M8_GNSS_BLOCKS),
        }
        for i, (gnss, res, most, on) in enumerate(_M8_GNSS_BLOCKS, start=1):
            kw |= {
                f"gnssId_{i:02d}": gnss,
                f"resTrkCh_{i:02d}": res,
                f"maxTrkCh_{i:02d}": most,
                f"enable_{i:02d}": on,
                f"sigCfMask_{i:02d}": 0x01,
            }
        steps = [
            CfgStep(
                "CFG-GNSS GPS, QZSS and BeiDou B1I on; SBAS, Galileo, IMES, GLONASS off",
                bytes(UBXMessage("CFG", "CFG-GNSS", SET, **kw).serialize()),
            ),
            CfgStep(
                f"CFG-RATE measRate={period_ms} ms, navRate=1, timeRef=GPS",
                bytes(
                    UBXMessage(
                        "CFG", "CFG-RATE", SET, measRate=period_ms, navRate=1, timeRef=1
                    ).serialize()
                ),
            ),
        ]
        for name, cls, mid in MEASUREMENT_MESSAGES:
            rates = {_CFG_MSG_PORT[port]: 1}
            msg = UBXMessage("CFG", "CFG-MSG", SET, msgClass=cls, msgID=mid, **rates)
            steps.append(
                CfgStep(f"CFG-MSG {name} rate 1 on {port.upper()}", bytes(msg.serialize()))
            )
        return steps
    suffix = _VALSET_PORT[port]
    return [
        _valset([("CFG_SIGNAL_BDS_ENA", 1), ("CFG_SIGNAL_BDS_B1_ENA", 1)]),
        _valset([("CFG_BDS_USE_GEO_PRN", 1)]),
        _valset([("CFG_RATE_MEAS", period_ms), ("CFG_RATE_NAV", 1)]),
        *(
            _valset([(f"CFG_MSGOUT_UBX_{name.replace('-', '_')}_{suffix}", 1)])
            for name, _, _ in MEASUREMENT_MESSAGES
        ),
    ]


def save_step(setup: ReceiverSetup, steps: Sequence[CfgStep]) -> CfgStep:
    """The message that keeps ``steps`` over a power cycle: CFG-CFG (M8: save the current
    configuration to BBR, flash, EEPROM, SPI flash) or one CFG-VALSET of all their keys to
    the BBR and flash layers (F9/X20)."""
    if setup.model == "m8":
        msg = UBXMessage(
            "CFG",
            "CFG-CFG",
            SET,
            clearMask=b"\x00\x00\x00\x00",
            saveMask=b"\x1f\x1f\x00\x00",
            loadMask=b"\x00\x00\x00\x00",
            devBBR=1,
            devFlash=1,
            devEEPROM=1,
            devSpiFlash=1,
        )
        return CfgStep("CFG-CFG save the configuration (BBR, flash)", bytes(msg.serialize()))
    keys = [kv for s in steps for kv in s.keys]
    return _valset(keys, LAYER_BBR | LAYER_FLASH)


class Link(Protocol):
    """A byte link to the receiver (a pyserial ``Serial`` with a short read timeout)."""

    @property
    def in_waiting(self) -> int: ...

    def write(self, data: bytes) -> int | None: ...

    def read(self, size: int = 1) -> bytes: ...

    def flush(self) -> None: ...

    def reset_input_buffer(self) -> None: ...


@dataclass(slots=True)
class SetupResult:
    """What the receiver answered: the steps it acknowledged, and whether it saved them."""

    acked: list[CfgStep] = field(default_factory=list)
    refused: list[CfgStep] = field(default_factory=list)
    saved: bool = False


class _AckReader:
    """UBX-ACK-ACK / ACK-NAK frames from whatever the device sends, within a deadline."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.reset()

    def reset(self) -> None:
        """Forget what was heard (at each message sent anew, after the input buffer was
        emptied)."""
        self.bytes_heard = 0
        # UBX frames only (NMEA, RTCM, garbage are skipped), payloads bounded by an ACK's: a
        # header claiming more is skipped at once (the framer resynchronises a byte
        # further), so it cannot hold an answer back
        self._framer = Framer(
            [p for p in PROTOCOLS if p.name == "ubx"], max_payload={"ubx": _ACK_PAYLOAD}
        )

    def answer(self, step: CfgStep, timeout_s: float) -> str | None:
        """``"ack"``, ``"nak"`` or None (nothing about ``step`` within ``timeout_s``): each
        read returns what the port holds or after ``_READ_TIMEOUT_S``, and the deadline is
        checked after each, so it holds (to a read) whatever the device sends."""
        deadline = time.monotonic() + timeout_s
        link = self.link
        while time.monotonic() < deadline:
            data = link.read(min(max(1, link.in_waiting), _READ_MAX))
            self.bytes_heard += len(data)
            for frame in self._framer.feed(data):
                raw = frame.raw
                if raw[2] != _ACK_CLASS or raw[3] not in (_ACK_ID, _NAK_ID):
                    continue
                if (raw[6], raw[7]) == step.ids:
                    return "ack" if raw[3] == _ACK_ID else "nak"
        return None


def _exchange(link: Link, reader: _AckReader, step: CfgStep, timeout_s: float) -> str | None:
    # what came before (the stream, a late answer to an earlier message of the same class
    # and id) is not the answer to this one
    link.reset_input_buffer()
    reader.reset()
    for attempt in (1, 2):
        link.write(step.raw)
        link.flush()
        got = reader.answer(step, timeout_s)
        if got is not None:
            log.info("%s: %s", "ACK" if got == "ack" else "NAK", step.what)
            return got
        log.info("no answer to %s (attempt %d)", step.what, attempt)
    return None


def _heard(n_bytes: int) -> str:
    return "the device sent nothing" if n_bytes == 0 else f"{n_bytes} bytes heard, none an answer"


def _in_effect(acked: Sequence[CfgStep]) -> str:
    if not acked:
        return "nothing was acknowledged"
    n = len(acked)
    return (
        f"the {n} message{'s' if n > 1 else ''} acknowledged before "
        "are in effect (RAM only, until a power cycle)"
    )


def run_setup(
    link: Link,
    steps: Sequence[CfgStep],
    *,
    timeout_s: float,
    save: CfgStep | None = None,
    name: str = "receiver",
) -> SetupResult:
    """Send ``steps`` one at a time, each awaiting its ACK/NAK (see the module docstring);
    then ``save`` if every step was acknowledged. Raises ReceiverSilentError (no answer,
    twice) or ReceiverRefusedError (any NAK), each one line naming what is in effect."""
    reader = _AckReader(link)
    result = SetupResult()
    for step in steps:
        got = _exchange(link, reader, step, timeout_s)
        if got is None:
            raise ReceiverSilentError(
                f"{name}: no answer (ACK/NAK) to {step.what} within {timeout_s:g} s, sent "
                f"twice ({_heard(reader.bytes_heard)}): not a u-blox receiver, a wrong baud "
                "rate, or its UBX input off; "
                + _in_effect(result.acked)
                + ("" if save is None else ", nothing saved")
            )
        (result.acked if got == "ack" else result.refused).append(step)
    if result.refused:
        what = "; ".join(s.what for s in result.refused)
        n = len(result.acked)
        raise ReceiverRefusedError(
            f"{name}: the receiver refused (ACK-NAK) {what}; the other {n} message"
            f"{'s' if n != 1 else ''} were acknowledged and are in effect (RAM only, until a "
            "power cycle)" + ("" if save is None else ", nothing saved")
        )
    if save is not None:
        got = _exchange(link, reader, save, timeout_s)
        if got is None:
            raise ReceiverSilentError(
                f"{name}: no answer (ACK/NAK) to {save.what} within {timeout_s:g} s, sent "
                "twice; the set-up is in effect in RAM, perhaps not saved"
            )
        if got == "nak":
            raise ReceiverRefusedError(
                f"{name}: the receiver refused (ACK-NAK) {save.what}; the set-up is in "
                "effect in RAM only, not saved"
            )
        result.saved = True
    return result


def configure_device(
    device: str, baud: int, setup: ReceiverSetup, *, save: bool = False
) -> SetupResult:
    """Open ``device`` at ``baud``, set ``setup`` up on it (:func:`run_setup`), close it.

    The port the measurements go to is ``setup.port`` (``auto``: USB for ``/dev/ttyACM*``,
    else UART1). A device that cannot be opened is InputError (exit 3)."""
    port = setup.port_for(device)
    steps = setup_steps(setup, port)
    try:
        link = serial.Serial(device, baud, timeout=_READ_TIMEOUT_S, write_timeout=setup.timeout_s)
    except (OSError, serial.SerialException, ValueError) as err:
        code = getattr(err, "errno", None)
        why = os.strerror(code) if isinstance(code, int) and code > 0 else str(err)
        raise InputError(f"{device}: cannot open: {why}") from err
    try:
        link.reset_input_buffer()
        return run_setup(
            link,
            steps,
            timeout_s=setup.timeout_s,
            save=save_step(setup, steps) if save else None,
            name=f"{device} ({setup.model}, port {port})",
        )
    except serial.SerialTimeoutException as err:
        raise ReceiverSilentError(
            f"{device}: writing timed out after {setup.timeout_s:g} s (flow control?)"
        ) from err
    except (OSError, serial.SerialException) as err:
        raise InputError(f"{device}: {err}") from err
    finally:
        link.close()
