"""What a user asks of a u-blox receiver's set-up (``bdsfix configure``, and ``bdsfix run``
with ``configure = true``): the receiver family, the measurement rate, the port its output
goes to and how long to wait for each acknowledgement.

Declared once with :func:`service.core.settings.setting`: ``bdsfix configure`` takes them as
``--model``, ``--rate-hz``, ``--port`` and ``--timeout-s``; the daemon's config file and
flags as ``configure_model``, ``configure_rate_hz``, ... (:data:`DAEMON_PREFIX`). The
messages themselves are built by :mod:`drivers.ubx_setup`.
"""

from __future__ import annotations

from dataclasses import dataclass

from service.core.settings import setting

MODELS = ("m8", "f9", "x20")
"""u-blox families: M8 (CFG-GNSS, CFG-MSG, CFG-RATE); F9 and X20 (CFG-VALSET keys)."""

PORTS = ("auto", "uart1", "uart2", "usb", "spi", "i2c")
"""Receiver port the measurements are enabled on; ``auto``: USB for a ``/dev/ttyACM*``
device (u-blox USB CDC-ACM), UART1 otherwise."""

DAEMON_PREFIX = "configure_"
"""Prefix of these settings among the daemon's keys (``configure_model``, ...)."""


@dataclass(frozen=True, slots=True)
class ReceiverSetup:
    """The set-up asked of a u-blox receiver (see the module docstring)."""

    model: str = setting("f9", "u-blox receiver family", kind="str", choices=MODELS)
    rate_hz: float = setting(
        10.0,
        "measurement rate set on the receiver [Hz]",
        kind="float",
        low=0.0,
        high=40.0,
        low_open=True,
    )
    port: str = setting(
        "auto",
        "receiver port that gets RXM-RAWX, RXM-MEASX and RXM-SFRBX (auto: usb for "
        "/dev/ttyACM*, else uart1)",
        kind="str",
        choices=PORTS,
    )
    timeout_s: float = setting(
        1.0,
        "wait for each ACK/NAK [s] (a message unanswered is sent once more)",
        kind="float",
        low=0.01,
        high=60.0,
    )

    @property
    def meas_period_ms(self) -> int:
        """CFG-RATE measRate / CFG-RATE-MEAS: the measurement period [ms] (at least 25)."""
        return max(25, round(1000.0 / self.rate_hz))

    def port_for(self, device: str | None) -> str:
        """The port name (``uart1`` ...) for ``device``, resolving ``auto``."""
        if self.port != "auto":
            return self.port
        name = (device or "").rsplit("/", 1)[-1]
        return "usb" if name.startswith("ttyACM") else "uart1"
