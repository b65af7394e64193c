#!/usr/bin/env python3
"""One MatNet-contract model from several, and from each model's view of
the photo's mirror image: an ensemble in a single ONNX file that matflow
runs like any other (`matflow predict --model OUT`).

Every pass runs one model on the photo, or on the photo mirrored left to
right (`--flip`); a mirrored pass's outputs are mirrored back, its
normals' x negated (the camera frame's x points right). The passes are
then averaged per pixel:

  depth                the geometric mean (the models' z in the scenes'
                       units; log z is what their losses compare)
  albedo, roughness,   the mean
  metallic
  normal               the mean, renormalised

Inputs are models written by `train.py` (outputs depth, albedo,
roughness, metallic, normal; fixed square input; metadata matflow.depth
= z); the first model's metadata is kept and `matflow.ensemble` says what
was combined. Every model's weights are stored once, however many passes
use them.

    python3 train/matnet/ensemble.py models/matnet_rooms.onnx --flip \\
        --out out/matnet/candidates/flip/matnet_rooms.onnx

The output is checked against onnxruntime running the inputs one by one
on a random photo (and its mirror); the largest difference is printed.
"""

import argparse
import hashlib
import os
import sys

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

NAMES = ["depth", "albedo", "roughness", "metallic", "normal"]
CHANNELS = [1, 3, 1, 1, 3]


def fail(msg):
    sys.exit(f"ensemble.py: {msg}")


def check_contract(path, m):
    outs = [o.name for o in m.graph.output]
    if outs != NAMES:
        fail(f"{path}: outputs {outs}, expected {NAMES}")
    if len(m.graph.input) != 1:
        fail(f"{path}: {len(m.graph.input)} inputs, expected one image")
    dims = m.graph.input[0].type.tensor_type.shape.dim
    if len(dims) != 4 or not all(d.HasField("dim_value") for d in dims[1:]) or dims[2].dim_value != dims[3].dim_value:
        fail(f"{path}: input must be [N, 3, S, S] with a fixed S")
    meta = {p.key: p.value for p in m.metadata_props}
    if meta.get("matflow.depth") != "z":
        fail(f"{path}: metadata matflow.depth = {meta.get('matflow.depth')!r}, expected 'z'")
    for n in m.graph.node:
        for a in n.attribute:
            if a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS):
                fail(f"{path}: node {n.name} has a subgraph; not supported")
    return dims[2].dim_value, {d.domain: d.version for d in m.opset_import}


def add_pass(graph, m, model_tag, pass_tag, source):
    """Copies model `m`'s nodes into `graph` reading `source` as its image;
    weights named `model_tag/…` (added by the caller once), other values
    `pass_tag/…`. Returns the pass's output value names in NAMES order."""
    inits = {t.name for t in m.graph.initializer}
    image = m.graph.input[0].name

    def rename(v):
        if v == "":
            return v
        if v == image:
            return source
        if v in inits:
            return f"{model_tag}/{v}"
        return f"{pass_tag}/{v}"

    for k, n in enumerate(m.graph.node):
        c = onnx.NodeProto()
        c.CopyFrom(n)
        c.name = f"{pass_tag}/{n.name or f'{n.op_type}#{k}'}"
        del c.input[:]
        c.input.extend(rename(v) for v in n.input)
        del c.output[:]
        c.output.extend(rename(v) for v in n.output)
        graph.node.append(c)
    return [rename(o.name) for o in m.graph.output]


def build(paths, flip):
    raw = []
    for p in paths:
        with open(p, "rb") as f:
            raw.append(f.read())
    models = [onnx.load_from_string(b) for b in raw]
    sizes = set()
    opsets = None
    for p, m in zip(paths, models):
        s, ops = check_contract(p, m)
        sizes.add(s)
        opsets = ops if opsets is None else opsets
        if ops.get("", 0) != opsets.get("", 0):
            fail(f"{p}: opset {ops.get('')} differs from the first model's {opsets.get('')}")
    if opsets.get("", 0) < 13:
        fail(f"opset {opsets.get('', 0)}: the averaging needs 13 or later (train.py exports 17)")
    if len(sizes) != 1:
        fail(f"models take different input sizes {sorted(sizes)}")
    size = sizes.pop()

    g = helper.make_graph([], "matnet_ensemble", [], [])
    g.input.extend([models[0].graph.input[0]])
    g.input[0].name = "image"
    g.initializer.append(numpy_helper.from_array(np.array(1e-8, np.float32), "ens/eps"))
    g.initializer.append(numpy_helper.from_array(np.array([1], np.int64), "ens/axes"))
    if flip:
        # The mirror: gather along the width with the indices reversed.
        g.initializer.append(numpy_helper.from_array(np.arange(size - 1, -1, -1, dtype=np.int64), "ens/reverse"))
        mirror_n = np.array([-1.0, 1.0, 1.0], np.float32).reshape(1, 3, 1, 1)
        g.initializer.append(numpy_helper.from_array(mirror_n, "ens/mirror_n"))
        g.node.append(helper.make_node("Gather", ["image", "ens/reverse"], ["ens/image_mirrored"], axis=3, name="ens/mirror_in"))

    passes = []
    for j, m in enumerate(models):
        for t in m.graph.initializer:
            c = onnx.TensorProto()
            c.CopyFrom(t)
            c.name = f"m{j}/{t.name}"
            g.initializer.append(c)
        for f in [False, True] if flip else [False]:
            tag = f"m{j}{'f' if f else ''}"
            outs = add_pass(g, m, f"m{j}", tag, "ens/image_mirrored" if f else "image")
            if f:
                back = []
                for name, o in zip(NAMES, outs):
                    r = f"{tag}/{name}_unmirrored"
                    g.node.append(helper.make_node("Gather", [o, "ens/reverse"], [r], axis=3, name=r))
                    if name == "normal":
                        r2 = f"{tag}/normal_x_negated"
                        g.node.append(helper.make_node("Mul", [r, "ens/mirror_n"], [r2], name=r2))
                        r = r2
                    back.append(r)
                outs = back
            passes.append(outs)

    k = len(passes)
    g.initializer.append(numpy_helper.from_array(np.array(1.0 / k, np.float32), "ens/share"))

    def mean(values, name, out=None):
        """The mean of `values` as `out` (default ens/NAME_mean)."""
        acc = values[0]
        for i, v in enumerate(values[1:]):
            s = f"ens/{name}_sum{i}"
            g.node.append(helper.make_node("Add", [acc, v], [s], name=s))
            acc = s
        out = out or f"ens/{name}_mean"
        g.node.append(helper.make_node("Mul", [acc, "ens/share"], [out], name=f"ens/{name}_share"))
        return out

    logs = []
    for i, p in enumerate(passes):
        lg = f"ens/depth_log{i}"
        g.node.append(helper.make_node("Log", [p[0]], [lg], name=lg))
        logs.append(lg)
    g.node.append(helper.make_node("Exp", [mean(logs, "log_depth")], ["depth"], name="ens/depth"))
    for c, name in enumerate(NAMES[1:4], start=1):
        mean([p[c] for p in passes], name, out=name)
    n = mean([p[4] for p in passes], "normal")
    g.node.append(helper.make_node("Mul", [n, n], ["ens/n2"], name="ens/n2"))
    g.node.append(helper.make_node("ReduceSum", ["ens/n2", "ens/axes"], ["ens/n2sum"], keepdims=1, name="ens/n2sum"))
    g.node.append(helper.make_node("Add", ["ens/n2sum", "ens/eps"], ["ens/n2eps"], name="ens/n2eps"))
    g.node.append(helper.make_node("Sqrt", ["ens/n2eps"], ["ens/nlen"], name="ens/nlen"))
    g.node.append(helper.make_node("Div", [n, "ens/nlen"], ["normal"], name="ens/normal"))

    for name, ch in zip(NAMES, CHANNELS):
        g.output.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, ["N", ch, size, size]))

    out = helper.make_model(g, opset_imports=[helper.make_opsetid(d, v) for d, v in opsets.items()])
    out.ir_version = models[0].ir_version
    for p in models[0].metadata_props:
        q = out.metadata_props.add()
        q.key, q.value = p.key, p.value
    desc = [f"{os.path.basename(p)} (sha256 {hashlib.sha256(b).hexdigest()[:16]})" for p, b in zip(paths, raw)]
    q = out.metadata_props.add()
    q.key = "matflow.ensemble"
    q.value = f"{k} passes: " + ", ".join(desc) + (", each also on the mirrored photo" if flip else "")
    onnx.checker.check_model(out)
    return out, size, k


def verify(paths, flip, out_path, size):
    import onnxruntime as ort

    rng = np.random.default_rng(0)
    x = rng.random((1, 3, size, size), dtype=np.float32)
    runs = []
    for p in paths:
        s = ort.InferenceSession(p, providers=["CPUExecutionProvider"])
        runs.append(s.run(None, {s.get_inputs()[0].name: x}))
        if flip:
            r = s.run(None, {s.get_inputs()[0].name: x[..., ::-1].copy()})
            r = [v[..., ::-1] for v in r]
            r[4] = r[4] * np.array([-1.0, 1.0, 1.0], np.float32).reshape(1, 3, 1, 1)
            runs.append(r)
    want = [np.exp(np.mean([np.log(r[0]) for r in runs], 0))]
    want += [np.mean([r[c] for r in runs], 0) for c in (1, 2, 3)]
    n = np.mean([r[4] for r in runs], 0)
    want.append(n / np.sqrt((n * n).sum(1, keepdims=True) + 1e-8))
    s = ort.InferenceSession(out_path, providers=["CPUExecutionProvider"])
    got = s.run(None, {"image": x})
    return max(float(np.abs(a - b).max()) for a, b in zip(got, want))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", nargs="+", help="models written by train.py")
    ap.add_argument("--flip", action="store_true", help="each model also on the mirrored photo")
    ap.add_argument("--out", required=True, help="the ensemble's .onnx")
    a = ap.parse_args()
    for p in a.models:
        if not os.path.isfile(p):
            fail(f"{p}: no such file")
    m, size, k = build(a.models, a.flip)
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    # Written beside the output and moved there once checked: a failed run
    # leaves no model behind.
    tmp = a.out + ".partial"
    onnx.save(m, tmp)
    err = verify(a.models, a.flip, tmp, size)
    if not err < 1e-4:
        os.remove(tmp)
        fail(f"the ensemble does not match its passes (max difference {err:.2e})")
    os.replace(tmp, a.out)
    print(f"{a.out}: {k} passes, {os.path.getsize(a.out) / 1e6:.1f} MB; max |ensemble - mean of passes| = {err:.2e}")


if __name__ == "__main__":
    main()
