"""Time each exported graph in ONNX Runtime on this machine (contract-sized inputs).

    python -m cmr.bench --models ../models [--repeats 20]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from .export import NUM_POINTS, example_inputs


def session(path: Path, threads: int) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def time_graph(sess: ort.InferenceSession, feeds: dict, repeats: int) -> float:
    sess.run(None, feeds)  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sess.run(None, feeds)
        times.append(time.perf_counter() - t0)
    return 1000.0 * float(np.median(times))


def bench(models_dir: Path, repeats: int = 20, threads: int = 2) -> dict:
    out = {}
    for name, kwargs in [("point_encoder", dict(num_points=NUM_POINTS)), ("image_encoder", {}),
                         ("frustum_head", dict(num_points=NUM_POINTS)), ("agent", dict(batch=1))]:
        sess = session(models_dir / f"{name}.onnx", threads)
        names = [i.name for i in sess.get_inputs()]
        feeds = {n: t.numpy() for n, t in zip(names, example_inputs(name, **kwargs))}
        out[f"{name}_ms"] = round(time_graph(sess, feeds, repeats), 2)
    out["onnxruntime"] = ort.__version__
    out["load_average_1min"] = os.getloadavg()[0]  # the machine is shared: read timings with this
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--models", type=Path, default=Path(__file__).resolve().parents[2] / "models")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    print(json.dumps(bench(args.models, args.repeats, args.threads), indent=2))


if __name__ == "__main__":
    main()
