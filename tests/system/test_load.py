"""Load, the short version of bench/bench_load.py (harness in tests/support/load.py): one
minute of a simulated 20 Hz receiver through `bdsfix run` at full speed with 50 ZeroMQ
subscribers, 20 NMEA TCP clients (5 never read) and a subscriber that reconnects every
20 FIX. Functional checks only (the timings are printed by the bench): no FIX lost for any
healthy peer, every non-reader dropped, the daemon's RSS flat after warm-up."""

from __future__ import annotations

from tests.support.load import make_stream, run_load


def test_load_no_fix_lost_slow_clients_dropped_rss_flat(tmp_path):
    stream = tmp_path / "stream.ubx"
    epochs = make_stream(stream, minutes=1.0)
    assert epochs == 1200
    res = run_load(stream, epochs, tmp_path, n_zmq=50, n_nmea=20, n_slow=5, rss_samples=40)
    assert res.daemon_rc == 0, res.daemon_stderr[-2000:]
    assert "Traceback" not in res.daemon_stderr
    # the daemon published one FIX per epoch (its own JSONL) ...
    assert res.jsonl_fixes == epochs
    st = res.status
    assert st["zmq_FIX"] == epochs and st.get("zmq_dropped", 0) == 0
    # ... and every healthy peer received all of them
    assert res.sub_fixes == [epochs] * 50
    assert res.nmea_gga == [epochs] * 15
    # the five non-readers, and only they, were dropped
    assert st["nmea_clients_accepted"] == 20
    assert st["nmea_clients_dropped_slow"] == 5
    # the reconnecting subscriber came and went many times and got messages in between
    assert res.reconnects >= 50 and res.reconnect_fixes > 0
    # the loop's own timing made it to STATUS (its values are the bench's business)
    assert st["epoch_loop_p99_ms"] > 0 and st["epoch_publish_p99_ms"] > 0
    # RSS: sampled throughout, flat within 10 % after warm-up (20 % of the epochs)
    assert len(res.rss_kb) >= 10
    ref, peak, growth = res.rss_growth_after_warmup(0.2)
    assert ref > 0 and growth <= 0.10, (ref, peak, res.rss_kb)
