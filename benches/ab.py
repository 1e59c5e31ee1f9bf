#!/usr/bin/env python3
"""Latency ratios of plans, variants or readi builds, in alternating rounds.

    python3 benches/ab.py [--threads 2] [--rounds 15] [--runs 10] CONFIG CONFIG ...

Each CONFIG is `PLAN`, `PLAN:VARIANT` or `READI_BINARY:PLAN[:VARIANT]` (a first part that
does not end in `.plan` is the binary; the default is this workspace's release build).
Every round runs `readi bench` once per config, in order, and takes its median; the report
gives each config's median over the rounds and the median (and range) of its per-round
ratio to the first config. On a shared host whose speed drifts, only such ratios from one
run mean anything. Examples:

    # a variant against the base plan
    python3 benches/ab.py base.plan adapted.plan:gamma=0.5
    # two builds of readi on one plan
    python3 benches/ab.py /tmp/readi-old:m.plan target/release/readi:m.plan
"""

import argparse
import os
import re
import statistics
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
READI = os.path.join(ROOT, "target", "release", "readi")


def parse(config):
    parts = config.split(":")
    binary = READI
    if len(parts) > 1 and not parts[0].endswith(".plan"):
        binary, parts = parts[0], parts[1:]
    plan = parts[0]
    variant = parts[1] if len(parts) > 1 else None
    return binary, plan, variant


def median_ms(binary, plan, variant, threads, runs):
    cmd = [binary, "bench", plan, "--threads", str(threads), "--runs", str(runs)]
    if variant:
        cmd += ["--variant", variant]
    out = subprocess.run(cmd, capture_output=True, text=True)
    m = re.search(r"median ([0-9.]+) ms", out.stdout)
    if not m:
        sys.exit(f"{' '.join(cmd)} failed:\n{out.stderr}")
    return float(m.group(1))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--runs", type=int, default=10, help="timed runs of each `readi bench` call")
    ap.add_argument("configs", nargs="+")
    args = ap.parse_args()
    configs = [parse(c) for c in args.configs]
    times = [[] for _ in configs]
    for r in range(args.rounds):
        for i, (binary, plan, variant) in enumerate(configs):
            times[i].append(median_ms(binary, plan, variant, args.threads, args.runs))
        print(f"round {r + 1}/{args.rounds}", file=sys.stderr, flush=True)
    for config, t in zip(args.configs, times):
        ratios = [a / b for a, b in zip(t, times[0])]
        print(
            f"{config:<60} median {statistics.median(t):8.2f} ms   ratio to the first "
            f"{statistics.median(ratios):.3f} (rounds {min(ratios):.3f}..{max(ratios):.3f})"
        )


if __name__ == "__main__":
    main()
