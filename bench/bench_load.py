"""Load: the daemon fed a simulated 20 Hz receiver at full speed, with many slow and fast peers.

`bdsfix simulate` writes a UBX stream (default 1 hour at 20 Hz). The bench plays the
receiver: `bdsfix run` connects to it over TCP (``--source tcp:``), and once every peer has
joined the bench writes the whole stream as fast as the daemon reads it. Peers, all real
sockets in this process:

- 50 ZeroMQ SUB sockets (FIX + STATUS) that read everything;
- 20 NMEA TCP clients: 15 read everything (GGA counted), 5 never read (small receive
  buffer), which the daemon must drop (``nmea_clients_dropped_slow``);
- 1 SUB socket closed and reopened every 20 FIX (1 s of data) for the whole run.

The harness is tests/support/load.py (shared with tests/system/test_load.py).

Figures: epoch loop time p50/p99/max (solve + publish, from the daemon's STATUS, so a
publisher that blocked would show here), publish time alone, slow clients dropped, FIX
records received by each healthy subscriber vs the daemon's JSONL, GGA per healthy NMEA
client, the daemon's RSS sampled from /proc/PID/status and its growth after warm-up.

Run: python bench/bench_load.py [--minutes 60] [--zmq-subs 50] [--nmea 20] [--slow 5]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.support.load import RATE_HZ, LoadResult, make_stream, run_load  # noqa: E402


def report(res: LoadResult) -> None:
    st = res.status
    print(
        f"  epochs {res.epochs_expected}, JSONL FIX records {res.jsonl_fixes}, wall "
        f"{res.wall_s:.1f} s ({res.jsonl_fixes / max(res.wall_s, 1e-9):.0f} epochs/s)"
    )
    print(
        "  epoch loop (solve + publish) p50 {:.2f} ms, p99 {:.2f} ms, max {:.1f} ms; "
        "publish alone p50 {:.2f} ms, p99 {:.2f} ms, max {:.1f} ms".format(
            *(
                st.get(f"epoch_{k}_{q}_ms", float("nan"))
                for k in ("loop", "publish")
                for q in ("p50", "p99", "max")
            )
        )
    )
    print(
        f"  NMEA clients accepted {st.get('nmea_clients_accepted', 0)}, dropped as slow "
        f"{st.get('nmea_clients_dropped_slow', 0)}, left {st.get('nmea_clients', 0)}"
    )
    s = res.sub_fixes
    print(
        f"  ZeroMQ: {len(s)} subscribers got FIX min {min(s)} max {max(s)} "
        f"(published {st.get('zmq_FIX', 0)}, JSONL {res.jsonl_fixes}); "
        f"{sum(x == res.jsonl_fixes for x in s)} complete; zmq_dropped {st.get('zmq_dropped', 0)}"
    )
    g = res.nmea_gga
    print(
        f"  NMEA: {len(g)} healthy clients got GGA min {min(g)} max {max(g)}; "
        f"{sum(x == res.jsonl_fixes for x in g)} complete"
    )
    print(f"  reconnecting subscriber: {res.reconnects} connections, {res.reconnect_fixes} FIX")
    ref, peak, growth = res.rss_growth_after_warmup()
    step = max(1, len(res.rss_kb) // 20)
    series = ", ".join(f"{t:.0f}s:{kb / 1024:.1f}" for t, kb, _ in res.rss_kb[::step])
    print(f"  daemon RSS [MiB] over time: {series}")
    print(
        f"  RSS after warm-up (20 % of epochs): {ref / 1024:.1f} MiB -> peak {peak / 1024:.1f} "
        f"MiB ({100 * growth:+.1f} %)"
    )
    print(f"  daemon exit {res.daemon_rc}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="simulated data [min]")
    ap.add_argument("--zmq-subs", type=int, default=50)
    ap.add_argument("--nmea", type=int, default=20)
    ap.add_argument("--slow", type=int, default=5)
    ap.add_argument("--keep", action="store_true", help="keep the work directory")
    a = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="bdsfix-load-"))
    stream = work / "stream.ubx"
    t0 = time.perf_counter()
    n = make_stream(stream, a.minutes)
    print(
        f"bench_load: {a.minutes:g} min at {RATE_HZ:g} Hz = {n} epochs, "
        f"{stream.stat().st_size / 1e6:.1f} MB UBX (simulated in {time.perf_counter() - t0:.0f} s)"
    )
    res = run_load(stream, n, work, n_zmq=a.zmq_subs, n_nmea=a.nmea, n_slow=a.slow)
    report(res)
    if not a.keep:
        for p in sorted(work.rglob("*"), reverse=True):
            p.unlink() if p.is_file() else p.rmdir()
        work.rmdir()
    else:
        print(f"  work directory: {work}")
    if "Traceback" in res.daemon_stderr:
        print(res.daemon_stderr[-3000:])


if __name__ == "__main__":
    main()
