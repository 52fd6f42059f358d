"""A flood of NMEA TCP connections against `bdsfix run` (harness in tests/support/flood.py):
one minute of a simulated 20 Hz receiver at full speed while this process opens up to
2,000 connections at a time, wave after wave, the daemon at the usual 1024-descriptor soft
limit and the default cap of 64 clients. Functional checks only (the loop timing with and
without the flood is bench/bench_flood.py's): the healthy client gets every epoch's GGA,
the connections over the cap are refused and counted, the daemon exits 0 without a
traceback."""

from __future__ import annotations

from service.output.sinks.nmea_tcp import LISTEN_BACKLOG
from tests.support.flood import run_flood
from tests.support.load import make_stream


def test_flood_of_connections_leaves_the_healthy_client_whole(tmp_path):
    stream = tmp_path / "stream.ubx"
    epochs = make_stream(stream, minutes=1.0)
    res = run_flood(epochs, tmp_path, stream=stream, n_flood=2000, max_clients=64)
    assert res.daemon_rc == 0, res.daemon_stderr[-2000:]
    assert "Traceback" not in res.daemon_stderr
    assert res.flood_size >= 500, "this process may not open enough descriptors"
    # the flood got in: at least one whole wave, the stream sent while waves went on
    assert res.waves >= 1 and res.flood_connected >= res.flood_size
    # the healthy client (connected before the flood) got every epoch's GGA
    assert res.jsonl_fixes == epochs
    assert res.gga == epochs
    st = res.status
    # the cap held: whatever did not fit under it was refused and counted
    assert st["nmea_clients"] <= 64
    assert st["nmea_clients_refused"] >= res.flood_size - 64
    # every connection was served or refused (the last ones may still wait in the backlog)
    served = st["nmea_clients_accepted"] - 1 + st["nmea_clients_refused"]
    assert served >= res.flood_connected - LISTEN_BACKLOG
    # with 64 clients at most the daemon never ran out of descriptors
    assert st.get("nmea_accept_errors", 0) == 0
    # the loop's timing reached STATUS (its values are the bench's)
    assert st["epoch_loop_p99_ms"] > 0
    # refusals are logged rarely, not once per connection
    refusals_logged = res.daemon_stderr.count("refused")
    assert 1 <= refusals_logged <= 3, res.daemon_stderr[-2000:]
