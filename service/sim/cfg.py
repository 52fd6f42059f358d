"""The virtual receiver's configuration interface: it answers UBX CFG messages as a u-blox
receiver does, and keeps the state they set (which measurement messages it outputs on its
port, whether it uses BeiDou GEOs, its measurement period).

Answers (u-blox F9 Interface Description, UBX-ACK and UBX-CFG-VALSET; M8 Protocol
Specification, UBX-CFG-GNSS/MSG/RATE/CFG): every CFG message gets UBX-ACK-ACK or UBX-ACK-NAK
with its class and id; anything else (polls, other classes) gets no answer. A CFG-VALSET is
atomic: one key refused refuses the message and none of its keys is applied. Supported:

- ``CFG-SIGNAL-BDS_ENA``, ``CFG-SIGNAL-BDS_B1_ENA`` and CFG-GNSS (the BeiDou block): BeiDou
  B1I on or off; a change restarts tracking, as on a real receiver (:attr:`restart`);
  CFG-GNSS with BeiDou on also uses the GEOs (an M8 has no separate switch);
- ``CFG-BDS-USE_GEO_PRN``: GEOs used (tracked and output) or not;
- ``CFG-RATE-MEAS`` / CFG-RATE ``measRate``: a multiple of the simulator's own epoch period
  (epochs in between are not output); ``CFG-RATE-NAV`` / ``navRate`` only 1;
  ``CFG-RATE-TIMEREF`` / ``timeRef`` any;
- ``CFG-MSGOUT-UBX_RXM_{RAWX,MEASX,SFRBX}_<PORT>`` / CFG-MSG of those three: output on or
  off; only the receiver's own port (``port``) changes what it sends, other ports are
  acknowledged and have no effect here;
- CFG-VALSET to the BBR/flash layers and CFG-CFG: acknowledged (nothing to keep here).

Everything else in the CFG class is refused (NAK), as are the keys or messages named in
``nak`` (to emulate a receiver that lacks them), and VALSET transactions. ``silent``: never
answer (a receiver at another baud rate, or not a u-blox).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Any

from pyubx2 import GET, SET, UBXMessage
from pyubx2.ubxtypes_configdb import UBX_CONFIG_DATABASE

log = logging.getLogger(__name__)

OUTPUTS = ("RXM-SFRBX", "RXM-MEASX", "RXM-RAWX")
"""The measurement messages the virtual receiver can output (in its epoch order)."""
_OUTPUT_IDS = {(0x02, 0x13): "RXM-SFRBX", (0x02, 0x14): "RXM-MEASX", (0x02, 0x15): "RXM-RAWX"}
PORTS = ("uart1", "uart2", "usb", "spi", "i2c")
_CFG_MSG_RATE = {
    "uart1": "rateUART1",
    "uart2": "rateUART2",
    "usb": "rateUSB",
    "spi": "rateSPI",
    "i2c": "rateDDC",
}
_BEIDOU = 3  # CFG-GNSS gnssId


def key_id(name: str) -> int | None:
    """The configuration key ID of a pyubx2 key name (``CFG_RATE_MEAS``, or the
    ``CFG_0x...`` pyubx2 gives keys it does not know); None if it is neither."""
    if name in UBX_CONFIG_DATABASE:
        return int(UBX_CONFIG_DATABASE[name][0])
    if name.startswith("CFG_0x"):
        try:
            return int(name[4:], 16)
        except ValueError:
            return None
    return None


def _key(name: str) -> int:
    kid = key_id(name)
    if kid is None:  # pragma: no cover - names below are pyubx2's own
        raise KeyError(name)
    return kid


_SIGNAL_KEYS = {_key("CFG_SIGNAL_BDS_ENA"): "bds_ena", _key("CFG_SIGNAL_BDS_B1_ENA"): "b1_ena"}
_GEO_KEY = _key("CFG_BDS_USE_GEO_PRN")
_RATE_MEAS, _RATE_NAV, _RATE_TIMEREF = (
    _key("CFG_RATE_MEAS"),
    _key("CFG_RATE_NAV"),
    _key("CFG_RATE_TIMEREF"),
)


def _msgout_keys() -> dict[int, tuple[str, str]]:
    """MSGOUT key ID -> (output, port) for the three measurement messages on every port."""
    out = {}
    for name in OUTPUTS:
        for port in PORTS:
            out[_key(f"CFG_MSGOUT_UBX_{name.replace('-', '_')}_{port.upper()}")] = (name, port)
    return out


_MSGOUT = _msgout_keys()


def _ack(msg: UBXMessage, ok: bool) -> bytes:
    cls, mid = msg.msg_cls[0], msg.msg_id[0]
    ident = "ACK-ACK" if ok else "ACK-NAK"
    return bytes(UBXMessage("ACK", ident, GET, clsID=cls, msgID=mid).serialize())


class CfgResponder:
    """The configuration state of the virtual receiver and its answers to CFG messages."""

    def __init__(
        self,
        *,
        port: str = "uart1",
        base_period_ms: int = 100,
        nak: Iterable[str] = (),
        silent: bool = False,
        outputs: Iterable[str] = (),
        use_geo: bool = False,
    ) -> None:
        if port not in PORTS:
            raise ValueError(f"port {port!r}: expected one of {', '.join(PORTS)}")
        self.port = port
        self.base_period_ms = base_period_ms
        self.silent = silent
        self.outputs: set[str] = set(outputs)
        self.use_geo = use_geo
        self.bds_on = True
        self.meas_period_ms = base_period_ms
        self.restart = False  # set when the signal configuration changed; the owner clears it
        self.answered: list[tuple[str, bool]] = []  # (what, acked), for the log and tests
        self._nak_names = {n for n in nak if not n.startswith("CFG_")}
        self._nak_keys = set()
        for n in nak:
            if n.startswith("CFG_"):
                kid = key_id(n)
                if kid is None:
                    raise ValueError(f"unknown configuration key {n!r}")
                self._nak_keys.add(kid)

    def handle(self, msg: Any) -> bytes:
        """The answer to one message from the host (a parsed UBXMessage): ACK, NAK or
        nothing (``b""``)."""
        if self.silent or not isinstance(msg, UBXMessage) or msg.msg_cls != b"\x06":
            return b""
        if msg.msgmode != SET:  # a poll: not answered here
            return b""
        ident = msg.identity
        if ident in self._nak_names:
            ok = False
        elif ident == "CFG-VALSET":
            ok = self._valset(msg)
        elif ident == "CFG-GNSS":
            ok = self._gnss(msg)
        elif ident == "CFG-RATE":
            ok = self._rate(int(msg.measRate), int(msg.navRate))
        elif ident == "CFG-MSG":
            ok = self._msg(msg)
        else:
            ok = ident == "CFG-CFG"
        self.answered.append((ident, ok))
        log.info("%s %s", "ACK" if ok else "NAK", msg)
        return _ack(msg, ok)

    # -- the messages -------------------------------------------------------------------

    def _valset(self, msg: UBXMessage) -> bool:
        if int(getattr(msg, "action", 0)) != 0:
            return False  # transactions are not supported here
        keys: dict[int, Any] = {}
        for name, value in vars(msg).items():
            if name.startswith("CFG_"):
                kid = key_id(name)
                if kid is None:
                    return False
                keys[kid] = value
        if not keys or any(k in self._nak_keys for k in keys):
            return False
        ram = bool(getattr(msg, "ram", 0))
        new_period = self.meas_period_ms
        for kid, value in keys.items():
            if kid in _SIGNAL_KEYS or kid in _MSGOUT or kid in (_GEO_KEY, _RATE_TIMEREF):
                continue
            if kid == _RATE_MEAS:
                if not self._period_ok(int(value)):
                    return False
                new_period = int(value)
            elif kid == _RATE_NAV:
                if int(value) != 1:
                    return False
            else:
                return False
        if not ram:
            return True  # BBR/flash only: nothing to keep in a virtual receiver
        self.meas_period_ms = new_period
        signals = {_SIGNAL_KEYS[k]: bool(v) for k, v in keys.items() if k in _SIGNAL_KEYS}
        if signals:
            self._set_bds(
                signals.get("bds_ena", self.bds_on) and signals.get("b1_ena", self.bds_on)
            )
        if _GEO_KEY in keys:
            self.use_geo = bool(keys[_GEO_KEY])
        for kid, value in keys.items():
            if kid in _MSGOUT:
                name, port = _MSGOUT[kid]
                if port == self.port:
                    self._set_output(name, int(value) > 0)
        return True

    def _gnss(self, msg: UBXMessage) -> bool:
        n = int(msg.numConfigBlocks)
        for i in range(1, n + 1):
            if int(getattr(msg, f"gnssId_{i:02d}")) == _BEIDOU:
                on = bool(getattr(msg, f"enable_{i:02d}"))
                self._set_bds(on)
                self.use_geo = on
        return True

    def _rate(self, meas_ms: int, nav: int) -> bool:
        if not self._period_ok(meas_ms) or nav != 1:
            return False
        self.meas_period_ms = meas_ms
        return True

    def _msg(self, msg: UBXMessage) -> bool:
        name = _OUTPUT_IDS.get((int(msg.msgClass), int(msg.msgID)))
        if name is None:
            return False
        self._set_output(name, int(getattr(msg, _CFG_MSG_RATE[self.port])) > 0)
        return True

    # -- state ----------------------------------------------------------------------------

    def _period_ok(self, ms: int) -> bool:
        return ms >= self.base_period_ms and ms % self.base_period_ms == 0

    def _set_bds(self, on: bool) -> None:
        self.restart = True  # a signal configuration written to RAM restarts tracking
        self.bds_on = on

    def _set_output(self, name: str, on: bool) -> None:
        if on:
            self.outputs.add(name)
        else:
            self.outputs.discard(name)
