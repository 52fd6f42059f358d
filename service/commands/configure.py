"""``bdsfix configure``: set a u-blox receiver up for the fast fix (:mod:`drivers.ubx_setup`).

BeiDou B1I on with its GEOs, RXM-RAWX, RXM-MEASX and RXM-SFRBX on the port in use, the
measurement rate; each message awaits its ACK/NAK. ``--dry-run`` prints the messages (hex
and what each asks) without opening anything; ``--save`` keeps the set-up over a power
cycle once every message was acknowledged. The run's outcome is one line on stderr; a NAK
(exit 5) or no answer (exit 3) is one error line naming what was refused and what is in
effect. ``bdsfix run`` with ``configure = true`` runs the same set-up
(:func:`setup_receiver`).
"""

from __future__ import annotations

import argparse
import logging
import os
import stat
import sys

from service.core.errors import ConfigError, InputError
from service.core.receiver_setup import ReceiverSetup
from service.core.settings import build, given

log = logging.getLogger(__name__)


def _device(source: str, baud: int) -> tuple[str, int]:
    """(device, baud) of a serial source; a source that is not one is a ConfigError."""
    from drivers.source import serial_device

    if source.startswith(("tcp:", "file:")) or source == "-":
        raise ConfigError(f"source {source!r}: configure needs a serial device or pty")
    device, rate = serial_device(source, baud)
    if not os.path.exists(device):
        raise InputError(f"{device}: no such device")
    if not stat.S_ISCHR(os.stat(device).st_mode):
        raise ConfigError(f"source {source!r}: configure needs a serial device or pty")
    return device, rate


def setup_receiver(source: str, baud: int, setup: ReceiverSetup, *, save: bool = False) -> str:
    """Set ``setup`` up on the receiver at ``source``; the one-line outcome (errors raise,
    see :func:`drivers.ubx_setup.run_setup`)."""
    from drivers.ubx_setup import configure_device

    device, rate = _device(source, baud)
    result = configure_device(device, rate, setup, save=save)
    kept = "saved to BBR and flash" if result.saved else "in RAM until a power cycle"
    return (
        f"{device}: {setup.model} receiver set up on {setup.port_for(device).upper()}: "
        f"{len(result.acked)} messages acknowledged, {setup.rate_hz:g} Hz, {kept}"
    )


def main_configure(args: argparse.Namespace) -> int:
    from drivers.source import serial_device
    from drivers.ubx_setup import save_step, setup_steps

    setup = build(ReceiverSetup, given(args, ReceiverSetup), {})
    if args.dry_run:
        device = serial_device(args.source, args.baud)[0] if args.source else None
        port = setup.port_for(device)
        steps = setup_steps(setup, port)
        if args.save:
            steps.append(save_step(setup, steps))
        for step in steps:
            print(f"{step.raw.hex()}  # {step.what}")
        print(
            f"bdsfix configure: dry run: {len(steps)} messages for a {setup.model} receiver, "
            f"measurements on {port.upper()}; nothing sent",
            file=sys.stderr,
        )
        return 0
    if not args.source:
        raise ConfigError("no receiver: give --source DEVICE (or --dry-run)")
    line = setup_receiver(args.source, args.baud, setup, save=args.save)
    print(f"bdsfix configure: {line}", file=sys.stderr)
    return 0
