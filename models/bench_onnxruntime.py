#!/usr/bin/env python3
"""onnxruntime's CPU forward time of models/vgg16_features.onnx, for `refnpr bench-vgg`.

Prints one JSON line: {"width", "height", "repeats", "forward_ms": [..], "forward_ms_median"}.
The input is a fixed-seed uniform [0,1] image, like the Rust benchmark's. onnxruntime
is only a yardstick here (pip install onnxruntime); the Rust code never uses it.
"""
import argparse
import json
import os
import time

import numpy as np
import onnxruntime as ort

ap = argparse.ArgumentParser()
ap.add_argument("--width", type=int, required=True)
ap.add_argument("--height", type=int, required=True)
ap.add_argument("--repeats", type=int, default=3)
args = ap.parse_args()
path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "vgg16_features.onnx")
sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
img = np.random.default_rng(0).uniform(0, 1, (1, 3, args.height, args.width)).astype(np.float32)
outputs = [o.name for o in sess.get_outputs()]
sess.run(outputs, {"image": img})  # warm-up
times = []
for _ in range(args.repeats):
    t = time.perf_counter()
    sess.run(outputs, {"image": img})
    times.append((time.perf_counter() - t) * 1e3)
print(json.dumps({"width": args.width, "height": args.height, "repeats": args.repeats,
                  "forward_ms": times, "forward_ms_median": float(np.median(times))}))
