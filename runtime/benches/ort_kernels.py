#!/usr/bin/env python3
"""readi's GEMM-based kernels against ONNX Runtime, same shapes, same thread count.

One command, from the workspace root, prints readi/ORT side by side:

    python3 runtime/benches/ort_kernels.py

It runs readi's criterion benchmarks (`cargo bench -p readi-runtime --bench kernels`;
it reads their medians from criterion's estimates.json files under $CARGO_TARGET_DIR,
else target/), then builds each shape as a single-op ONNX model (Conv + bias + Relu,
which ORT fuses; MatMul; Gemm for the linear), times ONNX Runtime on it with
intra_op_num_threads=2, and prints one table.

Options:
    --threads N          ORT intra-op threads (readi's bench uses 2; keep them equal)
    --cargo-args "..."   extra cargo arguments, e.g. "--features gemm/x86-v4"
    --no-cargo           do not run cargo; read the medians of the last criterion run
    --ort-level LEVEL    ORT graph optimisation: all (default; NCHWc convs), extended, basic
    --filter REGEX       only shapes whose name matches

Needs Python 3 with numpy, onnx and onnxruntime (`pip install onnxruntime onnx`). This
script and its Python packages are not part of the Rust build.
"""

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

# Must match RESNET18 in runtime/benches/kernels.rs: name, cin, h=w, cout, k, stride, pad.
RESNET18 = [
    ("conv1_7x7s2_3_64", 3, 224, 64, 7, 2, 3),
    ("l1_3x3_64", 64, 56, 64, 3, 1, 1),
    ("l2_3x3s2_64_128", 64, 56, 128, 3, 2, 1),
    ("l2_3x3_128", 128, 28, 128, 3, 1, 1),
    ("l3_3x3s2_128_256", 128, 28, 256, 3, 2, 1),
    ("l3_3x3_256", 256, 14, 256, 3, 1, 1),
    ("l4_3x3s2_256_512", 256, 14, 512, 3, 2, 1),
    ("l4_3x3_512", 512, 7, 512, 3, 1, 1),
    ("ds_1x1s2_64_128", 64, 56, 128, 1, 2, 0),
    ("ds_1x1s2_128_256", 128, 28, 256, 1, 2, 0),
    ("ds_1x1s2_256_512", 256, 14, 512, 1, 2, 0),
]
SGEMM = ("sgemm", "512x512x512", 512)
LINEAR = ("linear", "196x384x1536", (196, 384, 1536))


def workspace_root() -> Path:
    return Path(__file__).resolve().parents[2]


def criterion_dir() -> Path:
    target = os.environ.get("CARGO_TARGET_DIR")
    return (Path(target) if target else workspace_root() / "target") / "criterion"


def run_cargo(cargo_args: str, filt: str) -> None:
    cmd = ["cargo", "bench", "-p", "readi-runtime", "--bench", "kernels", *cargo_args.split(), "--", "--noplot", filt]
    print("+", " ".join(cmd), file=sys.stderr, flush=True)
    # Only the chosen conv algorithms: no READI_BENCH_ALL_ALGOS.
    env = {k: v for k, v in os.environ.items() if k != "READI_BENCH_ALL_ALGOS"}
    subprocess.run(cmd, cwd=workspace_root(), env=env, check=True, stdout=sys.stderr)


def median_ns(bench_dir: Path) -> float | None:
    est = bench_dir / "new" / "estimates.json"
    if not est.is_file():
        return None
    return json.loads(est.read_text())["median"]["point_estimate"]


def readi_conv(name: str) -> tuple[str, float] | None:
    """(algorithm, median ns) of the chosen algorithm's latest run for a conv layer."""
    layer = criterion_dir() / "conv2d" / name
    if not layer.is_dir():
        return None
    runs = [
        (d.joinpath("new", "estimates.json").stat().st_mtime, d.name, median_ns(d))
        for d in layer.iterdir()
        if d.is_dir() and not d.name.startswith("alt-") and d.name != "report" and median_ns(d) is not None
    ]
    if not runs:
        return None
    _, algo, ns = max(runs)
    return algo, ns


def ort_session(model, threads: int, level: str):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.graph_optimization_level = {
        "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
        "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
        "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
    }[level]
    return ort.InferenceSession(model.SerializeToString(), so, providers=["CPUExecutionProvider"])


def ort_median_s(sess, inputs: dict, samples: int = 30, sample_s: float = 0.05) -> float:
    """Median seconds per run, over `samples` samples of about `sample_s` each (I/O bound
    once, so only the kernel and ORT's per-run overhead are timed)."""
    import onnxruntime as ort

    binding = sess.io_binding()
    for name, arr in inputs.items():
        binding.bind_ortvalue_input(name, ort.OrtValue.ortvalue_from_numpy(arr))
    for out in sess.get_outputs():
        binding.bind_output(out.name)
    t0 = time.perf_counter()
    runs = 0
    while time.perf_counter() - t0 < 0.3 or runs < 5:  # warm-up, and iterations per sample
        sess.run_with_iobinding(binding)
        runs += 1
    per_sample = max(1, int(sample_s / ((time.perf_counter() - t0) / runs)))
    times = []
    for _ in range(samples):
        t = time.perf_counter()
        for _ in range(per_sample):
            sess.run_with_iobinding(binding)
        times.append((time.perf_counter() - t) / per_sample)
    return statistics.median(times)


def conv_model(cin, hw, cout, k, stride, pad):
    import numpy as np
    from onnx import TensorProto, helper, numpy_helper

    o = (hw + 2 * pad - k) // stride + 1
    rng = np.random.default_rng(0)
    w = numpy_helper.from_array((rng.standard_normal((cout, cin, k, k)) * (2 / (cin * k * k)) ** 0.5).astype(np.float32), "W")
    b = numpy_helper.from_array(rng.standard_normal(cout).astype(np.float32), "B")
    nodes = [
        helper.make_node("Conv", ["x", "W", "B"], ["c"], kernel_shape=[k, k], strides=[stride] * 2, pads=[pad] * 4),
        helper.make_node("Relu", ["c"], ["y"]),
    ]
    graph = helper.make_graph(
        nodes,
        "conv",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, cin, hw, hw])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, cout, o, o])],
        [w, b],
    )
    x = rng.standard_normal((1, cin, hw, hw)).astype(np.float32)
    return finish_model(graph), {"x": x}, 2 * cout * o * o * cin * k * k


def matmul_model(n):
    import numpy as np
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("MatMul", ["a", "b"], ["y"])],
        "matmul",
        [helper.make_tensor_value_info(v, TensorProto.FLOAT, [n, n]) for v in "ab"],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [n, n])],
    )
    rng = np.random.default_rng(1)
    feeds = {v: rng.standard_normal((n, n)).astype(np.float32) for v in "ab"}
    return finish_model(graph), feeds, 2 * n**3


def linear_model(rows, fin, fout):
    import numpy as np
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(2)
    w = numpy_helper.from_array(rng.standard_normal((fout, fin)).astype(np.float32), "W")
    b = numpy_helper.from_array(rng.standard_normal(fout).astype(np.float32), "B")
    graph = helper.make_graph(
        [helper.make_node("Gemm", ["x", "W", "B"], ["y"], transB=1)],
        "linear",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [rows, fin])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [rows, fout])],
        [w, b],
    )
    return finish_model(graph), {"x": rng.standard_normal((rows, fin)).astype(np.float32)}, 2 * rows * fin * fout


def finish_model(graph):
    from onnx import checker, helper

    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    checker.check_model(model)
    return model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cargo-args", default="")
    ap.add_argument("--no-cargo", action="store_true")
    ap.add_argument("--ort-level", default="all", choices=["all", "extended", "basic"])
    ap.add_argument("--filter", default="")
    args = ap.parse_args()
    try:
        import onnxruntime
    except ImportError:
        sys.exit("needs onnxruntime and onnx: pip install onnxruntime onnx")

    pick = re.compile(args.filter)
    rows = []  # (name, flops, criterion group, ORT model, ORT feeds)
    for name, cin, hw, cout, k, stride, pad in RESNET18:
        if pick.search(name):
            model, feeds, flops = conv_model(cin, hw, cout, k, stride, pad)
            rows.append((name, flops, "conv2d", model, feeds))
    if pick.search(SGEMM[1]):
        model, feeds, flops = matmul_model(SGEMM[2])
        rows.append((SGEMM[1], flops, "sgemm", model, feeds))
    if pick.search(LINEAR[1]):
        model, feeds, flops = linear_model(*LINEAR[2])
        rows.append((LINEAR[1], flops, "linear", model, feeds))

    if not args.no_cargo:
        names = "|".join(re.escape(r[0]) for r in rows)
        run_cargo(args.cargo_args, f"^(sgemm|conv2d|linear)/({names})(/|$)")

    print(f"ONNX Runtime {onnxruntime.__version__}, {args.threads} threads, optimisation level {args.ort_level};"
          " medians; readi/ORT is the time ratio (below 1: readi faster)")
    head = f"{'shape':<20} {'readi algo':<10} {'readi us':>9} {'GFLOP/s':>8} {'ORT us':>9} {'GFLOP/s':>8} {'readi/ORT':>9}"
    print(head + "\n" + "-" * len(head), flush=True)
    for name, flops, group, model, feeds in rows:
        if group == "conv2d":
            got = readi_conv(name)
            algo, ns = got if got else ("-", None)
        else:
            algo, ns = "gemm", median_ns(criterion_dir() / group / name)
        ort_s = ort_median_s(ort_session(model, args.threads, args.ort_level), feeds)
        r_us = ns / 1e3 if ns else float("nan")
        o_us = ort_s * 1e6
        print(
            f"{name:<20} {algo:<10} {r_us:>9.1f} {flops / r_us / 1e3:>8.1f} {o_us:>9.1f} {flops / o_us / 1e3:>8.1f}"
            f" {r_us / o_us:>9.2f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
