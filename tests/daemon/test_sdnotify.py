"""sd_notify datagrams received on a real AF_UNIX socket, as systemd would."""

import socket

from service.daemon.sdnotify import Notifier


def test_ready_and_watchdog_reach_the_socket(tmp_path):
    path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(path)
    srv.settimeout(60)  # the datagrams are there at once; only a hang waits
    try:
        n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "30000000"})
        assert n.enabled and n.watchdog_interval_s == 15.0
        assert n.ready("tracking")
        assert srv.recv(256) == b"READY=1\nSTATUS=tracking"
        assert n.watchdog()
        assert srv.recv(256) == b"WATCHDOG=1"
    finally:
        srv.close()


def test_without_systemd_it_is_silent():
    n = Notifier({})
    assert not n.enabled and not n.ready() and n.watchdog_interval_s is None
