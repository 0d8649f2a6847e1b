"""Soak: the live node over a long run, fed the real RSS bags in a loop at real time.

    python -m localization.benchmarks.soak [--minutes 30] [--window 5] [--particles N] [--json]

The same set-up as ``localization.benchmarks.latency`` (the node in its own process with
``config/real_params.yaml`` and its particle count, every scan updating the filter, the three real
RACECAR bags streamed at real time, one after the other, round after round). Each message is
restamped with the wall clock as it is sent, so the node's clock runs on; after each bag the car stands
for 0.1 s, its odometry going on (a VESC's does), so the bag's last scan is reached; each bag's start is
a jump of the car back to that bag's start pose, sent as a new initial pose (as an operator would after
carrying the car back).

Prints, per ``--window`` minutes of stream: scans, scan stamp → pose latency median and p95, and the
node's resident memory at the window's end; then the memory growth after the first minute, the
change of p95 latency from the first window to the last, the scans that got no pose (dropped), the
node's own count of the scans it received, processed and did not use (a scan sent but not received was
lost by the best-effort transport, as a lidar's scans are sent), and the node's CPU share. Targets:
memory growth ≤ 10 MB after the first minute, the last window's p95 within 10 % of the first's, no
scan dropped.
"""
from __future__ import annotations

import argparse
import json
import sys

from localization.benchmarks.latency import measure_latency


def format_soak(r: dict) -> str:
    if "error" in r:
        return f"soak: not measured ({r['error']})"
    lines = [f"soak: live node, {r['particles']} particles, {r['ray_caster']}, every scan updating, real RSS bags "
             f"in a loop at real time for {r['duration_s'] / 60:.0f} min",
             "  window start (min)   scans   latency median (ms)   p95 (ms)   node RSS at end (MB)"]
    for w in r["windows"]:
        med = "n/a" if w["latency_ms_median"] is None else f"{w['latency_ms_median']:.1f}"
        p95 = "n/a" if w["latency_ms_p95"] is None else f"{w['latency_ms_p95']:.1f}"
        rss = "n/a" if w["rss_mb_end"] is None else f"{w['rss_mb_end']:.0f}"
        lines.append(f"  {w['start_s'] / 60:18.1f}   {w['scans']:5d}   {med:>19}   {p95:>8}   {rss:>20}")
    full = [w for w in r["windows"] if w["latency_ms_p95"] is not None]
    change = (full[-1]["latency_ms_p95"] / full[0]["latency_ms_p95"] - 1.0) if len(full) > 1 else None
    growth, cpu = r["rss_growth_after_first_minute_mb"], r["node_cpu_share"]
    lines.append("  memory growth after the first minute: " + ("n/a" if growth is None else f"{growth:+.1f} MB")
                 + "; p95 latency, last window vs first: " + ("n/a" if change is None else f"{100 * change:+.1f} %")
                 + f"; dropped scans (no pose): {r['scans_skipped']} of {r['scans_sent']}; node CPU "
                 + ("n/a" if cpu is None else f"{100 * cpu:.1f} % of one core"))
    # a scan sent but never received was lost by the (best-effort, as a lidar's) transport, not by the node
    lines.append(f"  the node's own count: {r.get('node_scan_counts') or 'not reported'}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m localization.benchmarks.soak", description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=30.0, help="minutes of stream (default 30)")
    ap.add_argument("--window", type=float, default=5.0, help="minutes per reported window (default 5)")
    ap.add_argument("--particles", type=int, default=None, help="default: the parameter file's")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    progress = None if args.json else (lambda msg: print(msg, file=sys.stderr, flush=True))
    r = measure_latency(args.particles, 60.0 * args.minutes, params_file=None, progress=progress,
                        window=60.0 * args.window)
    print(json.dumps(r) if args.json else format_soak(r))
    return 1 if "error" in r else 0


if __name__ == "__main__":
    sys.exit(main())
