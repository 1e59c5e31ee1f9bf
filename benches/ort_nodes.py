#!/usr/bin/env python3
"""readi against ONNX Runtime node by node: where a model's time differs.

    python3 benches/ort_models.py --models mobilenet_v2 --keep   # prints DIR
    python3 benches/ort_nodes.py DIR mobilenet_v2 [--threads 1] [--top 25]

Reads the plan (`MODEL.plan`) and the ONNX export (`MODEL-b1.onnx`) that
`ort_models.py --keep` left in DIR, profiles ORT over `--runs` runs (its per-node
`_kernel_time` events) and readi over as many (`readi bench --profile --steps 0`), and
pairs each readi step with the ORT nodes of the layers it computes: an ORT node path such
as `/features/features.2/features.2.0/block/block.1/block.1.0/Conv` names the PyTorch
module `features.2.0.block.1.0`, and a readi step lists the modules it fused
(`features.2.0.block.1.0 (+features.2.0.block.1.1, features.2.0.block.1.2)`). Prints
the steps by how much longer readi took than ORT's matched nodes, and the ORT time no
step matched.

Both profiles add their own overhead, and at two threads ORT's per-node times include
its threads' hand-offs, so compare rows within one run; whole-model ratios come from
`ort_models.py`. Needs onnxruntime (pip); nothing here is part of the Rust build.
"""

import argparse
import collections
import json
import os
import re
import subprocess

import numpy as np
import onnxruntime as ort

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
READI = os.path.join(ROOT, "target", "release", "readi")


def module_of(node_name):
    """The PyTorch module path an ORT node name carries, or None: the exporter writes
    each module's path component by component (`/features/features.2/features.2.0/...`),
    then the operator (`Conv`, `Mul/QuickGeluFusion`, `Relu_output_0_nchwc`)."""
    path = []
    for part in (p for p in node_name.split("/") if p):
        if path and part.startswith(path[-1] + "."):
            path[-1] = part
        else:
            path.append(part)
    while path and path[-1][:1].isupper():
        path.pop()
    return ".".join(path) if path else None


def ort_name(module):
    """readi's name of a repeated call, `relu#1`, as the exporter writes it, `relu_1`."""
    name, _, k = module.partition("#")
    return f"{name}_{k}" if k and k != "0" else name


def ort_times(onnx_path, threads, runs):
    """Mean milliseconds per run of each module's ORT nodes."""
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.enable_profiling = True
    session = ort.InferenceSession(onnx_path, so, providers=["CPUExecutionProvider"])
    inp = session.get_inputs()[0]
    shape = [d if isinstance(d, int) else 1 for d in inp.shape]
    x = np.random.default_rng(0).random(shape, dtype=np.float32)
    for _ in range(runs):
        session.run(None, {inp.name: x})
    profile = session.end_profiling()
    with open(profile) as f:
        events = json.load(f)
    os.remove(profile)
    times = collections.defaultdict(float)
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            name = e["name"][: -len("_kernel_time")]
            times[module_of(name) or name] += e["dur"] / runs / 1000.0
    return times


def readi_steps(readi, plan, threads, runs):
    """(milliseconds, kind, step, fused modules) per readi step."""
    cmd = [readi, "bench", plan, "--threads", str(threads), "--runs", str(runs), "--profile", "--steps", "0"]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    steps = []
    for line in out.splitlines():
        m = re.match(r"\s+([0-9.]+) ms\s+(\S+)\s+(\S+)(.*)", line)
        if m:
            fused = re.findall(r"([A-Za-z_0-9.#]+)[,)]", m.group(4))
            modules = [ort_name(name) for name in [m.group(3)] + fused]
            steps.append((float(m.group(1)), m.group(2), m.group(3), modules))
    return steps


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dir", help="the directory ort_models.py --keep printed")
    ap.add_argument("model", help="a model name, as in ort_models.py (mobilenet_v2, resnet50, ...)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--runs", type=int, default=20, help="profiled runs on each side")
    ap.add_argument("--top", type=int, default=25, help="rows to print")
    ap.add_argument("--readi", default=READI, help="the readi binary")
    args = ap.parse_args()

    ort_ms = ort_times(os.path.join(args.dir, f"{args.model}-b1.onnx"), args.threads, args.runs)
    steps = readi_steps(args.readi, os.path.join(args.dir, f"{args.model}.plan"), args.threads, args.runs)
    rows = []
    for ms, kind, step, modules in steps:
        matched = sum(ort_ms.pop(m, 0.0) for m in dict.fromkeys(modules))
        rows.append((ms - matched, ms, matched, kind, step))
    rows.sort(reverse=True)
    print(
        f"{args.model}, {args.threads} thread(s): readi steps {sum(r[1] for r in rows):.3f} ms, "
        f"ORT matched {sum(r[2] for r in rows):.3f} ms, ORT unmatched {sum(ort_ms.values()):.3f} ms"
    )
    print(f"{'readi - ORT':>11}  {'readi':>7}  {'ORT':>7}  step")
    for diff, ms, matched, kind, step in rows[: args.top]:
        print(f"{diff:+11.3f}  {ms:7.3f}  {matched:7.3f}  {kind:14s} {step}")
    left = sorted(((v, k) for k, v in ort_ms.items() if v > 0.01), reverse=True)[:10]
    if left:
        print("ORT time no step matched: " + ", ".join(f"{k} {v:.3f}" for v, k in left))


if __name__ == "__main__":
    main()
