"""``bdsfix run`` (the daemon), ``bdsfix replay`` and ``bdsfix sub``.

The daemon reads its TOML config (every key also a flag), loads the persisted ephemeris
store (the warm start the method assumes) plus any RINEX nav files, opens the receiver
source and the outputs, tells systemd it is ready and keeps the watchdog fed. SIGTERM stops
it cleanly after saving the store; SIGHUP reopens file outputs. Only this module and the
CLI entry configure logging.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.commands.options import coarse_config, full_rule, solver_config, systems_of
from service.commands.summary import stream_lines
from service.core.ephemeris import EphemerisStore
from service.core.errors import EXIT_INTERRUPTED, EXIT_OK, BdsfixError, ConfigError, InputError
from service.core.systems import DEFAULT_SYSTEMS, parse_systems
from service.daemon.loop import Runner
from service.engine.pipeline import EpochResult, Pipeline
from service.engine.solver import IonoSet
from service.output.publish import Publishers
from service.output.sinks import OutputSpec, SinkOptions, open_sinks
from service.output.timeline import Timeline as BaseTimeline

if TYPE_CHECKING:
    from drivers.rinex import NavData
    from service.daemon.config import DaemonConfig

log = logging.getLogger(__name__)


OUTPUT_SETTINGS: dict[str, str] = {
    # the settings (TOML keys and flags of run and replay) that name one output each: kind
    "nmea_tcp": "nmea-tcp",
    "nmea_out": "nmea-file",
    "nmea_serial": "nmea-serial",
    "zmq": "zmq",
    "jsonl_out": "jsonl",
}


def output_specs(settings: Any) -> list[OutputSpec]:
    """The outputs ``settings`` (a DaemonConfig or replay's flags) ask for, in the order
    they are opened and fed: the named settings that are set, then each ``output``."""
    specs = [
        OutputSpec(kind, value)
        for key, kind in OUTPUT_SETTINGS.items()
        if (value := getattr(settings, key, None))
    ]
    return specs + [OutputSpec.parse(text) for text in getattr(settings, "output", None) or ()]


def build_publishers(
    specs: list[OutputSpec], talker: str = "GN", options: SinkOptions | None = None
) -> Publishers:
    """Open the outputs; one that fails closes the others and raises its own error."""
    return Publishers(open_sinks(specs, options), talker=talker)


def _check_source(spec: str) -> None:
    """A capture file given as the source must be there, readable and hold something bdsfix
    reads (:func:`drivers.source.check_capture`): one-line error, exit 3.

    Serial devices are opened at start by the caller (a device that vanishes later is
    waited for); TCP sources are retried, since the server may start after the daemon."""
    if spec == "-" or spec.startswith(("tcp:", "serial:", "/dev/")):
        return
    from drivers.source import check_capture, file_spec

    fmt, path = file_spec(spec)  # FORMAT:PATH names a registered file format
    if not os.path.exists(path):
        raise InputError(f"source {spec!r}: no such file or device")
    if os.path.isdir(path):
        raise InputError(f"source {spec!r}: is a directory")
    if os.path.isfile(path) and fmt is None:
        try:
            check_capture(path)
        except OSError as exc:
            raise InputError(f"source {spec!r}: cannot read: {exc.strerror}") from exc


def _check_nav(
    spec: str,
    nav: list[str],
    gps_week: int | None = None,
    systems: frozenset[str] = frozenset(DEFAULT_SYSTEMS),
) -> list[NavData]:
    """RINEX nav files without a BDS ephemeris, or (for a capture file source) of another
    day than its first epoch, refuse the start: one line, exit 3
    (:func:`service.commands.navcheck.check_navigation`, the rule ``solve`` follows). The
    files as read, for the source to put at the head of its stream."""
    from service.commands.navcheck import check_navigation, first_epoch_time, read_navigation

    if not nav:
        _check_needs_nav(spec, gps_week)
        return []
    navs = read_navigation(nav, systems)
    first = None
    if _is_regular_file(spec):
        first = first_epoch_time(spec.removeprefix("file:"), gps_week)
    check_navigation(nav, navs, first, systems)
    return navs


def _check_needs_nav(spec: str, gps_week: int | None) -> None:
    """A file of a format that carries no ephemerides bdsfix decodes
    (:attr:`drivers.protocols.FileFormat.needs_nav`), given without ``--nav``: one line
    naming the nav file of its first epoch's day, exit 3."""
    if not _is_regular_file(spec):
        return
    from drivers.source import file_format, file_spec
    from service.commands.navcheck import first_epoch_time
    from service.core.timebase import datetime_from_gpst

    fmt, path = file_spec(spec)
    fmt = fmt or file_format(path)
    if fmt is None or fmt.needs_nav is None or not fmt.needs_nav(Path(path)):
        return
    first = first_epoch_time(spec, gps_week)
    day = ""
    if first is not None:
        t = datetime_from_gpst(*first)
        doy = t.timetuple().tm_yday
        day = (
            f" of GPST {t:%Y-%m-%d} (day {doy:03d}), e.g. the IGS broadcast "
            f"BRDM00DLR_S_{t:%Y}{doy:03d}0000_01D_MN.rnx"
        )
    raise InputError(
        f"{path}: {fmt.describe} carries no ephemerides bdsfix decodes; give --nav with a "
        f"RINEX 3 nav file{day}"
    )


def _is_regular_file(spec: str) -> bool:
    """Whether the source ``spec`` names a regular file (not stdin, a device, a FIFO or TCP)."""
    if spec == "-" or spec.startswith(("tcp:", "serial:")):
        return False
    from drivers.source import file_spec

    return os.path.isfile(file_spec(spec)[1])


STATE_DIR_MODE = 0o700  # the state directory, when the daemon creates it


def _check_state_dir(state_dir: Path) -> None:
    """The ephemeris store's directory must be (or become) a writable directory.

    Created :data:`STATE_DIR_MODE` whatever the umask (its missing parents get the umask's
    default); an existing one open to group or others is left as it is, with a warning."""
    if state_dir.exists() and not state_dir.is_dir():
        raise InputError(f"state directory {state_dir}: not a directory")
    try:
        state_dir.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.mkdir(state_dir, STATE_DIR_MODE)
        except FileExistsError:
            mode = state_dir.stat().st_mode & 0o777
            if mode & ~STATE_DIR_MODE:
                log.warning(
                    "state directory %s has mode %04o: open to %s (the daemon creates it "
                    "%04o); left as it is",
                    state_dir,
                    mode,
                    "group or others, who may replace the ephemeris store"
                    if mode & 0o022
                    else "group or others",
                    STATE_DIR_MODE,
                )
        else:
            os.chmod(state_dir, STATE_DIR_MODE)  # exactly 0700: the umask may have narrowed it
    except OSError as exc:
        raise InputError(f"state directory {state_dir}: {exc.strerror}") from exc
    if not os.access(state_dir, os.W_OK | os.X_OK):
        raise InputError(f"state directory {state_dir}: not writable")


def load_store(state_dir: Path, max_age_s: float) -> EphemerisStore:
    from service.daemon.config import STORE_NAME

    path = state_dir / STORE_NAME
    if path.exists():
        try:
            store = EphemerisStore.load(path, max_age_s=max_age_s)
            log.info("warm start: %d ephemerides from %s", len(store), path)
            if store.refused:  # logged by the store; not kept on disk either
                try:
                    store.save(path)
                    log.info("%s rewritten without the %d sets refused", path, store.refused)
                except OSError as exc:
                    log.warning("%s: cannot rewrite it (%s); kept as it is", path, exc.strerror)
            return store
        except BdsfixError as exc:
            EphemerisStore.set_aside(path, exc)  # one WARNING line; the daemon starts empty
    return EphemerisStore(max_age_s=max_age_s)


def _open_ntrip(cfg: DaemonConfig) -> list[Any]:
    """One event source per NTRIP URL in ``nav`` (read by the loop in threads of their own;
    nothing is connected yet: a caster that is down at start is retried, see
    :mod:`drivers.ntrip`)."""
    from drivers.ntrip import open_ntrip
    from service.daemon.config import ntrip_sources

    return [
        open_ntrip(
            url,
            reconnect_max_s=cfg.ntrip_reconnect_max_s,
            header_timeout_s=cfg.ntrip_header_timeout_s,
        )
        for url in ntrip_sources(cfg)
    ]


class _Signals:
    """SIGTERM and SIGINT stop the runner cleanly (store saved, final STATUS); the exit code
    says which: 0 for SIGTERM (systemctl stop), 130 for Ctrl-C. SIGHUP reopens files."""

    def __init__(self, runner: Runner) -> None:
        self.interrupted = False
        signal.signal(signal.SIGTERM, lambda *_: runner.request_stop())
        signal.signal(signal.SIGINT, lambda *_: self._interrupt(runner))
        if hasattr(signal, "SIGHUP"):
            signal.signal(signal.SIGHUP, lambda *_: runner.request_reopen())

    def _interrupt(self, runner: Runner) -> None:
        self.interrupted = True
        runner.request_stop()

    def exit_code(self) -> int:
        return EXIT_INTERRUPTED if self.interrupted else EXIT_OK


def main_run(args: argparse.Namespace) -> int:
    # the daemon's configuration, state lock and systemd notifier here, not with the module:
    # ``bdsfix replay`` needs none of them (part of its start-up)
    from drivers.source import open_source
    from drivers.transport import RECONNECT_MAX_S, SerialTransport
    from service.daemon.config import (
        DEFAULT_CONFIG,
        STORE_NAME,
        load_config,
        nav_files,
        overrides_from_args,
    )
    from service.daemon.sdnotify import Notifier
    from service.daemon.statelock import lock_state_dir

    cfg_path = args.config
    if cfg_path is None and Path(DEFAULT_CONFIG).exists():
        cfg_path = DEFAULT_CONFIG
    cfg: DaemonConfig = load_config(cfg_path, overrides_from_args(args))
    logging.getLogger().setLevel(cfg.log_level.upper())
    if not cfg.source:
        raise ConfigError("no receiver source: set 'source' in the config or --source")
    specs = output_specs(cfg)
    # What can refuse to start (source, nav files, outputs) does so first, with one line.
    _check_source(cfg.source)
    systems = parse_systems(cfg.systems)
    navs = _check_nav(cfg.source, nav_files(cfg), systems=systems)
    _check_state_dir(cfg.resolved_state_dir())
    lock_state_dir(cfg.resolved_state_dir())  # a second daemon on it: exit 3, one line
    if cfg.configure:  # before the source opens: the set-up has the port to itself
        from service.commands.configure import setup_receiver

        log.info("receiver set-up: %s", setup_receiver(cfg.source, cfg.baud, cfg.setup))
    source = open_source(
        cfg.source,
        nav=navs or None,
        baud=cfg.baud,
        reconnect_max_s=RECONNECT_MAX_S,
        systems=systems,
    )
    nav_sources = _open_ntrip(cfg)
    transport = getattr(source, "transport", None)
    if isinstance(transport, SerialTransport):
        transport.open_now()  # a missing device at start is an error (exit 3)
    options = SinkOptions(
        baud=cfg.baud,
        append=True,
        zmq_curve_secret_key=cfg.zmq_curve_secret_key,
        zmq_curve_clients=cfg.zmq_curve_clients,
        nmea_tcp_max_clients=cfg.nmea_tcp_max_clients,
        http_max_clients=cfg.http_max_clients,
    )
    outputs = build_publishers(specs, cfg.talker, options)
    state_dir = cfg.resolved_state_dir()
    log.info("ephemeris store kept in %s", state_dir.resolve())
    store = load_store(state_dir, cfg.max_eph_age_s)
    timeline = Timeline()
    pipeline = Pipeline(
        store,
        IonoSet.of([store.iono]),
        cfg.solver,
        coarse=cfg.coarse,
    )
    notifier = Notifier()
    runner = Runner(
        source,
        pipeline,
        outputs,
        source_counters=source.counters,
        status_interval_s=cfg.status_interval_s,
        store_path=state_dir / STORE_NAME,
        store_save_interval_s=cfg.store_save_interval_s,
        watchdog=notifier.watchdog,
        watchdog_interval_s=notifier.watchdog_interval_s,
        silence_warn_s=cfg.silence_warn_s,
        nav_sources=[(src.name, src, src.counters) for src in nav_sources],
        nav_max_age_s=cfg.ntrip_max_age_s,
        on_result=timeline.log_first_fixes,
    )
    signals = _Signals(runner)
    notifier.ready(f"reading {cfg.source}")
    for src in nav_sources:
        log.info("network ephemerides from %s", src.name)
    log.info(
        "bdsfix running: source %s, outputs %s",
        cfg.source,
        ", ".join(f"{o.kind} {o.spec}" for o in specs) or "none",
    )
    try:
        n = runner.run()
    finally:
        notifier.stopping()
        source.close()
        for src in nav_sources:
            src.close()
        outputs.close()
    counters = runner.counters()
    # every counter, for the journal (a subscriber had them in the last STATUS record)
    log.info("final counters: %s", " ".join(f"{k}={v}" for k, v in sorted(counters.items())))
    for line in stream_lines("run", n, counters, runner.skipped()):
        print(line, file=sys.stderr)
    for line in timeline.lines() if n else []:  # as replay's (no epoch: no time scale)
        print(line, file=sys.stderr)
    return signals.exit_code()


class Timeline(BaseTimeline):
    """The stream's timeline (:class:`service.output.timeline.Timeline`), and for ``run``
    one INFO line at each first fix."""

    def log_first_fixes(self, r: EpochResult) -> None:
        """:meth:`on_result`, and one INFO line at the first fast and the first conventional
        fix: the data time since the first measurement, the fix's GPS time and position
        (what ``run`` tells the journal; the timeline follows at stop)."""
        for key in self.marks(r):
            if key.endswith(" fix"):
                fix = r.fix
                log.info(
                    "%s: t = %.2f s after the first measurement (GPST week %d, tow %.3f s), "
                    "%.7f %.7f %.1f m, %d satellites",
                    key,
                    self.first[key],
                    fix.gpst_week,
                    fix.gpst_tow_s,
                    fix.lat_deg,
                    fix.lon_deg,
                    fix.alt_m,
                    len(fix.used),
                )


def main_replay(args: argparse.Namespace) -> int:
    from drivers.source import open_source
    from drivers.transport import pace

    if args.speed is not None and not (args.speed > 0 and math.isfinite(args.speed)):
        raise ConfigError(f"--speed must be a positive number, got {args.speed}")
    asked = output_specs(args)
    specs = asked or [OutputSpec("nmea-file", "-")]  # none asked: NMEA to stdout
    cfg = solver_config(args)
    timeline = Timeline()
    offset = 0.0
    if not args.files:
        from service.sim.scenario import builtin_scenario

        events: Iterable[Any]
        systems = systems_of(args)
        nav = None
        if args.nav:  # a real nav file's satellites (GPS and Galileo too, with --systems)
            from service.commands.solve import load_navigation

            nav_store, nav_iono = load_navigation(list(args.nav), systems=systems)
            nav = (nav_store.all(), nav_iono)
        chunks, week, store, iono, offset, info = builtin_scenario(
            seed=args.seed, full_rule=full_rule(args), nav=nav, systems="".join(sorted(systems))
        )
        events = decode_chunks(chunks, week, systems)
        speed = args.speed if args.speed is not None else None
        counters: dict[str, int] = {}
        print(f"bdsfix replay: built-in scenario: {info}", file=sys.stderr)
    else:
        if len(args.files) > 1:
            raise ConfigError("replay takes one capture at a time (or none for the scenario)")
        store = EphemerisStore()
        iono = IonoSet()
        _check_source(args.files[0])
        systems = systems_of(args)
        navs = _check_nav(args.files[0], args.nav or [], args.gps_week, systems)
        src = open_source(args.files[0], nav=navs or None, gps_week=args.gps_week, systems=systems)
        events = src
        counters = src.counters
        speed = None if args.max_speed else (args.speed or 1.0)
    pipeline = Pipeline(
        store,
        iono,
        cfg,
        restart_at_s=args.restart_at,
        sync_seed=args.seed,
        full_rule=full_rule(args),
        coarse=coarse_config(args),
    )
    options = SinkOptions(
        nmea_tcp_max_clients=args.nmea_tcp_max_clients,
        http_max_clients=args.http_max_clients,
        timeline_offset_s=offset,  # the status page's timeline reads as the summary's
    )
    outputs = build_publishers(specs, args.talker, options)
    # what was opened, once it opened (an error stays the only line)
    if args.files:
        pacing = "as fast as possible" if speed is None else f"paced at {speed:g}x real time"
        hint = "" if speed is None else " (--max-speed: as fast as possible)"
        print(f"bdsfix replay: reading {args.files[0]}, {pacing}{hint}", file=sys.stderr)
    if asked and not any(o.kind == "nmea-file" and o.spec == "-" for o in asked):
        outs = ", ".join(f"{o.kind} {o.spec}" for o in asked)
        note = "no NMEA on stdout: add --nmea-out -"
        print(f"bdsfix replay: outputs {outs} ({note})", file=sys.stderr)
    runner = Runner(
        pace(events, speed),
        pipeline,
        outputs,
        source_counters=counters,
        status_interval_s=args.status_interval_s,
        on_result=timeline.on_result,
        # a capture file at full speed: no reader thread (see Runner.inline)
        inline=speed is None and bool(args.files) and _is_regular_file(args.files[0]),
    )
    signals = _Signals(runner)
    try:
        n = runner.run()
    finally:
        outputs.close()
    for line in stream_lines("replay", n, runner.counters(), runner.skipped()):
        print(line, file=sys.stderr)
    # no epoch, no time scale: a timeline of "(not reached)" would say nothing
    for line in timeline.lines(offset, restarted=args.restart_at is not None) if n else []:
        print(line, file=sys.stderr)
    return signals.exit_code()


SUB_NOTICE_AFTER_S = 3.0
"""``bdsfix sub`` says on stderr what it waits for when nothing came in this long [s]."""


def sub_topics(asked: list[str] | None) -> list[str]:
    """The ZeroMQ subscriptions for ``--topic`` values: the record classes, named in any
    case; an unknown one is refused with the list (a SUB socket would wait for it forever).
    None: every message."""
    from service.output.sinks.base import RECORD_CLASSES

    if not asked:
        return [""]
    topics = []
    for name in asked:
        topic = name.strip().upper()
        if topic not in RECORD_CLASSES:
            raise ConfigError(
                f"--topic {name!r}: no such topic; bdsfix publishes {', '.join(RECORD_CLASSES)}"
            )
        topics.append(topic)
    return topics


def main_sub(args: argparse.Namespace) -> int:
    """Print each ZeroMQ message as ``TOPIC JSON`` (``--json``: the JSON alone, one object
    per line, for jq). While no publisher is there it idles (reconnects back off to 5 s)
    and says so once on stderr; SIGTERM ends it with 0 (Ctrl-C: 130, as every command)."""
    import zmq

    topics = sub_topics(args.topic)
    endpoint = args.endpoint
    if "://" not in endpoint:
        raise ConfigError(
            f"endpoint {endpoint!r} names no transport: a ZeroMQ endpoint is "
            f"TRANSPORT://ADDRESS, e.g. tcp://{endpoint}"
        )
    ctx: Any = zmq.Context.instance()
    sock = ctx.socket(zmq.SUB)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RECONNECT_IVL, 200)
    sock.setsockopt(zmq.RECONNECT_IVL_MAX, 5000)  # back off while no publisher listens
    for topic in topics:
        sock.setsockopt_string(zmq.SUBSCRIBE, topic)
    _curve_client(sock, getattr(args, "curve_server_key", None), getattr(args, "curve_key", None))
    try:
        sock.connect(args.endpoint)
    except zmq.ZMQError as exc:
        sock.close()
        raise ConfigError(f"endpoint {args.endpoint!r}: {exc.strerror}") from exc
    stop = False

    def on_term(signum: int, frame: Any) -> None:
        nonlocal stop
        stop = True

    previous = signal.signal(signal.SIGTERM, on_term)
    n = 0
    idle_s = 0.0
    noticed = False
    try:
        while not stop and (args.count is None or n < args.count):
            slice_s = 0.5
            if not sock.poll(int(slice_s * 1000)):
                idle_s += slice_s
                if args.timeout_s and idle_s >= args.timeout_s:
                    break
                if not noticed and n == 0 and idle_s >= SUB_NOTICE_AFTER_S:
                    noticed = True
                    print(
                        f"bdsfix sub: no message from {args.endpoint} yet; waiting for a "
                        "publisher ('bdsfix run', or 'bdsfix replay --zmq ENDPOINT')",
                        file=sys.stderr,
                        flush=True,
                    )
                continue
            idle_s = 0.0
            topic, body = sock.recv_multipart()
            print(body.decode() if args.json else f"{topic.decode()} {body.decode()}", flush=True)
            n += 1
    finally:
        signal.signal(signal.SIGTERM, previous)
        sock.close()
    return 0


def _curve_client(sock: Any, server_key: str | None, client_key: str | None) -> None:
    """CURVE on a SUB socket: the server's public certificate and our own secret one."""
    if not server_key:
        if client_key:
            raise ConfigError("--curve-key needs --curve-server-key")
        return
    import zmq
    import zmq.auth

    try:
        server_public, _ = zmq.auth.load_certificate(server_key)
        if client_key:
            public, secret = zmq.auth.load_certificate(client_key)
        else:
            public, secret = zmq.curve_keypair()
    except (OSError, ValueError) as exc:
        raise ConfigError(f"ZeroMQ CURVE certificate: {exc}") from exc
    if not secret:
        raise ConfigError(f"--curve-key {client_key}: no secret-key in file")
    sock.curve_serverkey = server_public
    sock.curve_publickey = public
    sock.curve_secretkey = secret


def decode_chunks(
    chunks: Iterable[bytes], gps_week: int, systems: frozenset[str] = frozenset("C")
) -> Iterator[Any]:
    """Events of a byte stream through the production stream decoder (as from a receiver),
    reading the UBX of ``systems``."""
    from drivers.source import StreamDecoder

    options = {"ubx": {"systems": systems}} if systems != frozenset("C") else None
    dec = StreamDecoder(gps_week=gps_week, mapper_options=options)
    for data in chunks:
        yield from dec.feed(data)
    yield from dec.flush()
