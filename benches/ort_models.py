#!/usr/bin/env python3
"""readi against ONNX Runtime on whole models, same weights, same threads, one run.

From the workspace root:

    python3 benches/ort_models.py                   # ResNet-18, 1x3x224x224, 2 threads
    python3 benches/ort_models.py --threads 1 --rounds 5
    python3 benches/ort_models.py --models all --threads 1,2 --batch 1,8 --markdown
                                                    # every zoo model with a spec in models/,
                                                    # at 1 and 2 threads, batch 1 and 8, and
                                                    # the README table

For each model it
  1. builds the PyTorch module the spec describes (torchvision's ResNet-18; the ViT
     encoder of tests/fixtures/make_fixtures.py) with readi's seeded weights,
  2. writes the state_dict to safetensors and runs `readi compile` on the spec,
  3. exports the same module to ONNX,
  4. checks that readi and ORT agree on one input (max abs error),
  5. alternates `readi bench` and ORT timing for --rounds rounds (each round: --runs
     timed runs after warm-up) and reports the median over rounds of readi / ORT.

Needs torch, torchvision, onnx, onnxruntime and safetensors (pip). Builds readi in
release mode first. Nothing here is part of the Rust build or of CI.
"""

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch
import torchvision

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests", "fixtures"))
from make_fixtures import VitEncoder, seed_model  # noqa: E402

READI = os.path.join(ROOT, "target", "release", "readi")


# torchvision's zoo: each entry runs when its spec `models/<name>.readi` exists.
ZOO = [
    "resnet18",
    "resnet50",
    "mobilenet_v2",
    "mobilenet_v3_large",
    "efficientnet_b0",
    "convnext_tiny",
    "swin_t",
    "vit_b_16",
    "regnet_y_400mf",
]


def models():
    zoo = {
        name: (
            f"models/{name}.readi",
            [],
            (lambda name=name: getattr(torchvision.models, name)()),
            {"image": (1, 3, 224, 224)},
        )
        for name in ZOO
        if os.path.exists(os.path.join(ROOT, "models", f"{name}.readi"))
    }
    return {
        **zoo,
        # BEVFusion's parts at the nuScenes config's sizes (models/bevfusion/*.readi, the
        # plain-PyTorch ports of tests/fixtures/bevfusion/).
        "bevfusion_swin": ("models/bevfusion/swin.readi", [], bevfusion_swin, {"images": (6, 3, 256, 704)}),
        "bevfusion_decoder": (
            "models/bevfusion/decoder.readi",
            [],
            bevfusion_decoder,
            {"camera_bev": (1, 80, 180, 180), "lidar_bev": (1, 256, 180, 180)},
        ),
        "vit_encoder": (
            "models/vit_encoder.readi",
            [],
            lambda: VitEncoder(),
            {"image": (1, 3, 224, 224)},
        ),
    }


def bevfusion_swin():
    """mmdet's Swin-T as BEVFusion configures it (swin_ref.py), under BEVFusion's names."""
    sys.path.insert(0, os.path.join(ROOT, "tests", "fixtures", "bevfusion"))
    from swin_ref import SwinTransformer

    class Backbone(torch.nn.Module):
        def __init__(self):
            super().__init__()
            swin = SwinTransformer(96, [2, 2, 6, 2], [3, 6, 12, 24], 7)
            self.encoders = torch.nn.ModuleDict({"camera": torch.nn.ModuleDict({"backbone": swin})})

        def forward(self, images):
            return tuple(self.encoders["camera"]["backbone"](images))

    return Backbone()


def bevfusion_decoder():
    """ConvFuser, SECOND, SECONDFPN and the TransFusion head (make_bevfusion_fixtures.py),
    returning readi's outputs in readi's order (without the box coder's)."""
    sys.path.insert(0, os.path.join(ROOT, "tests", "fixtures", "bevfusion"))
    import types

    import make_bevfusion_fixtures as parts

    # The head's 1x1 max pool on [B, H, W] (the nuScenes classes kept whole) is the
    # identity; torch exports it as a MaxPool ONNX Runtime refuses, so it is left out.
    pool = parts.F.max_pool2d
    parts.F = types.SimpleNamespace(
        **{k: getattr(parts.F, k) for k in dir(parts.F) if not k.startswith("__") and k != "max_pool2d"},
        max_pool2d=lambda x, kernel_size, **kw: x if kernel_size == 1 else pool(x, kernel_size, **kw),
    )

    class Decoder(parts.Decoder):
        def forward(self, camera_bev, lidar_bev):
            fused = self.fuser([camera_bev, lidar_bev])
            bev = self.decoder["neck"](self.decoder["backbone"](fused))
            res = self.heads["object"](bev)
            names = ["dense_heatmap", "center", "height", "dim", "rot", "vel", "heatmap", "query_heatmap_score"]
            return (fused, bev) + tuple(res[n] for n in names)

    return Decoder(80, 256, 256, [128, 256], [5, 5], [256, 256], 128, 10, 200, 8, 256, 64)


def run(cmd):
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"command failed: {' '.join(cmd)}\n{r.stdout}\n{r.stderr}")
    return r.stdout


def readi_median(plan, threads, runs, batch=1):
    out = run([READI, "bench", plan, "--threads", str(threads), "--runs", str(runs), "--warmup", "3", "--batch", str(batch)])
    m = re.search(r"median ([0-9.]+) ms", out)
    return float(m.group(1))


ORT_RUN = """
import sys, numpy as np, onnxruntime as ort
so = ort.SessionOptions()
so.intra_op_num_threads = int(sys.argv[2])
so.inter_op_num_threads = 1
so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
feeds = dict(np.load(sys.argv[3]))
if sys.argv[1] != "-":
    ort.InferenceSession(sys.argv[1], so, providers=["CPUExecutionProvider"]).run(None, feeds)
# The peak of this process's memory since its exec (not ru_maxrss: Linux carries the
# parent's high-water mark through fork and exec).
print(next(l for l in open("/proc/self/status") if l.startswith("VmHWM:")).split()[1])
"""


def ort_rss_mib(*argv):
    """The peak resident memory (MiB) of a Python process running ORT_RUN on `argv`."""
    return int(run([sys.executable, "-c", ORT_RUN, *argv]).split()[-1]) / 1024


def peak_memory(plan, onnx_path, feeds, npys, threads, tmp):
    """Peak resident memory of one readi run (`readi bench --runs 1`, which reports it) and of
    one ORT session run, each in a process of its own; ORT's less that of a Python that
    imported onnxruntime and loaded the inputs but made no session (the interpreter's own
    share)."""
    feeds_path = os.path.join(tmp, "feeds.npz")
    np.savez(feeds_path, **feeds)
    out = run([READI, "bench", plan, "--threads", str(threads), "--runs", "1", "--warmup", "0"] + npys)
    readi = float(re.search(r"peak resident memory: ([0-9.]+) MiB", out).group(1))
    ort_rss = ort_rss_mib(onnx_path, str(threads), feeds_path)
    idle = ort_rss_mib("-", str(threads), feeds_path)
    return readi, ort_rss - idle


def ort_median(sess, feeds, runs):
    for _ in range(3):
        sess.run(None, feeds)
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        sess.run(None, feeds)
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", default="2", help="thread counts, comma-separated: 1,2")
    ap.add_argument("--batch", default="1", help="batch sizes of the zoo's image models, comma-separated: 1,8")
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument(
        "--models", default="resnet18", help="comma-separated (resnet18,vit_encoder), or `all`: the zoo's specs"
    )
    ap.add_argument(
        "--memory", action="store_true", help="also the peak resident memory of one run of each, in processes of their own"
    )
    ap.add_argument("--keep", action="store_true", help="keep the weights, plans and ONNX files")
    ap.add_argument("--markdown", action="store_true", help="end with the table as markdown")
    args = ap.parse_args()
    table = models()
    names = [n for n in ZOO if n in table] if args.models == "all" else args.models.split(",")
    unknown = [n for n in names if n not in table]
    if unknown:
        sys.exit(f"unknown model(s) {unknown}: known are {sorted(table)} (a zoo model needs models/<name>.readi)")
    thread_counts = [int(t) for t in args.threads.split(",")]
    batches = [int(b) for b in args.batch.split(",")]
    rows = []

    from safetensors.torch import save_file

    run(["cargo", "build", "--release", "-q", "--bin", "readi"])
    # Weights, plans and ONNX files take gigabytes for the whole zoo: they go with the run
    # unless --keep asks for them.
    if args.keep:
        tmp = tempfile.mkdtemp(prefix="readi-ort-")
        print(f"keeping weights, plans and ONNX files in {tmp}", file=sys.stderr, flush=True)
    else:
        tmp_dir = tempfile.TemporaryDirectory(prefix="readi-ort-")
        tmp = tmp_dir.name
    for name in names:
        spec, overrides, build, inputs = table[name]
        print(f"{name}: compiling and exporting", file=sys.stderr, flush=True)
        model = seed_model(build(), 1)
        weights = os.path.join(tmp, f"{name}.safetensors")
        save_file({k: v.contiguous() for k, v in model.state_dict().items()}, weights)
        plan = os.path.join(tmp, f"{name}.plan")
        run([READI, "compile", spec, "--weights", weights, "-o", plan] + overrides)

        ratios, memory = {}, {}
        # Only the zoo's image models take a batch; BEVFusion's parts keep their shapes.
        for batch in batches if name in ZOO else [1]:
            x = {k: torch.randn(batch, *s[1:]) if name in ZOO else torch.randn(*s) for k, s in inputs.items()}
            ratios.update(compare(name, plan, model, x, tmp, thread_counts, args, memory))
        rows.append((name, ratios, memory))

    if args.markdown:
        cols = [(t, b) for b in batches for t in thread_counts]
        heads = " | ".join(f"readi / ORT, {t} thread{'s' if t > 1 else ''}, batch {b}" for t, b in cols)
        print(f"\n| model | {heads} |")
        print("| --- |" + " --- |" * len(cols))
        for name, ratios, _ in rows:
            print(f"| {name} | " + " | ".join(f"{ratios[c]:.2f}" if c in ratios else "-" for c in cols) + " |")
        if args.memory:
            heads = " | ".join(f"{t} thread{'s' if t > 1 else ''}, batch {b}" for t, b in cols)
            print(f"\npeak resident memory, readi / ORT (MiB):\n\n| model | {heads} |")
            print("| --- |" + " --- |" * len(cols))
            for name, _, memory in rows:
                cells = [f"{memory[c][0]:.0f} / {memory[c][1]:.0f}" if c in memory else "-" for c in cols]
                print(f"| {name} | " + " | ".join(cells) + " |")


def compare(name, plan, model, x, tmp, thread_counts, args, memory):
    """readi / ORT at each thread count on inputs `x` (their leading size is the batch),
    alternating rounds; {(threads, batch): median ratio}."""
    import onnxruntime as ort
    from safetensors.numpy import load_file

    batch = next(iter(x.values())).shape[0]
    onnx_path = os.path.join(tmp, f"{name}-b{batch}.onnx")
    torch.onnx.export(model, tuple(x.values()), onnx_path, input_names=list(x), dynamo=False)
    feeds = {k: v.numpy() for k, v in x.items()}
    npys = []
    for k, v in feeds.items():
        p = os.path.join(tmp, f"{k}.npy")
        np.save(p, v)
        npys += ["--input", f"{k}={p}"]
    ratios = {}
    for threads in thread_counts:
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        sess = ort.InferenceSession(onnx_path, so, providers=["CPUExecutionProvider"])

        # Agreement on one input.
        out_path = os.path.join(tmp, "out.safetensors")
        run([READI, "run", plan, "--output", out_path, "--threads", str(threads)] + npys)
        readi_out = load_file(out_path)
        ort_out = sess.run(None, feeds)
        errs = [float(np.abs(a - b).max()) for a, b in zip(readi_out.values(), ort_out) if a.shape == b.shape]

        readi_t, ort_t = [], []
        for _ in range(args.rounds):
            # The inputs' leading size binds the spec's batch dimension (six views).
            readi_t.append(readi_median(plan, threads, args.runs, batch))
            ort_t.append(ort_median(sess, feeds, args.runs))
        # Each round is a pair measured back to back, so its ratio shares the machine's
        # state of the moment; the median of the pairs' ratios is the figure, the range
        # shows how noisy the run was.
        pairs = sorted(a / b for a, b in zip(readi_t, ort_t))
        ratio = statistics.median(pairs)
        ratios[(threads, batch)] = ratio
        r, o = statistics.median(readi_t), statistics.median(ort_t)
        if args.memory:
            mem_r, mem_o = peak_memory(plan, onnx_path, feeds, npys, threads, tmp)
            memory[(threads, batch)] = (mem_r, mem_o)
            print(f"{name}: batch {batch}, {threads} threads: peak resident memory readi {mem_r:.0f} MiB, "
                  f"ORT {mem_o:.0f} MiB (over an idle interpreter)", flush=True)
        print(
            f"{name}: batch {batch}, {threads} threads, {args.rounds} rounds x {args.runs} runs: "
            f"readi/ORT = {ratio:.2f} (pairs {pairs[0]:.2f}..{pairs[-1]:.2f}; "
            f"medians readi {r:.2f} ms, ORT {o:.2f} ms; "
            f"max abs error vs ORT {max(errs) if errs else float('nan'):.2e})",
            flush=True,
        )
    return ratios


if __name__ == "__main__":
    main()
