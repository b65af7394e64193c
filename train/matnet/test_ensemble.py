#!/usr/bin/env python3
"""Tests of ensemble.py (onnx and onnxruntime; `tests/predict.rs` runs it
in `cargo test`): on two small models of train.py's contract that are
not mirror-symmetric, the ensemble is the per-pixel combination its
documentation states, computed here independently; each model's weights
are stored once; models off the contract are refused by name.

  python3 train/matnet/test_ensemble.py"""
import os
import subprocess
import sys
import tempfile
import unittest

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

sys.dont_write_bytecode = True
HERE = os.path.dirname(os.path.abspath(__file__))
S = 16  # matflow's smallest input side


def small_model(path, seed, names=("depth", "albedo", "roughness", "metallic", "normal"), depth_meta="z"):
    """A model of train.py's contract: a 3x3 convolution with random
    (asymmetric) weights to 9 channels, then train.py's heads."""
    rng = np.random.default_rng(seed)
    w = rng.normal(0.0, 0.5, (9, 3, 3, 3)).astype(np.float32)
    inits = [numpy_helper.from_array(w, "w")]
    nodes = [helper.make_node("Conv", ["image", "w"], ["o"], pads=[1, 1, 1, 1])]

    def sl(c0, c1, out):
        tag = f"s{c0}"
        inits.extend(
            numpy_helper.from_array(np.array([v], np.int64), f"{tag}_{k}") for k, v in (("a", c0), ("b", c1), ("x", 1))
        )
        nodes.append(helper.make_node("Slice", ["o", f"{tag}_a", f"{tag}_b", f"{tag}_x"], [out]))

    sl(0, 1, "d0")
    sl(1, 4, "a0")
    sl(4, 5, "r0")
    sl(5, 6, "m0")
    sl(6, 9, "n0")
    nodes += [
        helper.make_node("Exp", ["d0"], [names[0]]),
        helper.make_node("Sigmoid", ["a0"], [names[1]]),
        helper.make_node("Sigmoid", ["r0"], [names[2]]),
        helper.make_node("Sigmoid", ["m0"], [names[3]]),
        helper.make_node("Tanh", ["n0"], ["nt"]),
        helper.make_node("Mul", ["nt", "nt"], ["n2"]),
        helper.make_node("ReduceSum", ["n2", "ax"], ["ns"], keepdims=1),
        helper.make_node("Sqrt", ["ns"], ["nl"]),
        helper.make_node("Div", ["nt", "nl"], [names[4]]),
    ]
    inits.append(numpy_helper.from_array(np.array([1], np.int64), "ax"))
    chans = [1, 3, 1, 1, 3]
    g = helper.make_graph(
        nodes,
        "small",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["N", 3, S, S])],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["N", c, S, S]) for n, c in zip(names, chans)],
        inits,
    )
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    for k, v in (("matflow.contract", "matnet"), ("matflow.depth", depth_meta)):
        p = m.metadata_props.add()
        p.key, p.value = k, v
    onnx.save(m, path)


def run(path, x):
    s = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    return s.run(None, {"image": x})


def ensemble(*args):
    return subprocess.run(
        [sys.executable, os.path.join(HERE, "ensemble.py"), *args],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )


class Ensemble(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.TemporaryDirectory()
        self.a = os.path.join(self.tmp.name, "a.onnx")
        self.b = os.path.join(self.tmp.name, "b.onnx")
        small_model(self.a, 1)
        small_model(self.b, 2)
        self.x = np.random.default_rng(3).random((1, 3, S, S), dtype=np.float32)

    def tearDown(self):
        self.tmp.cleanup()

    def test_two_models_and_their_mirrors_combine_as_documented(self):
        out = os.path.join(self.tmp.name, "ens.onnx")
        r = ensemble(self.a, self.b, "--flip", "--out", out)
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertIn("4 passes", r.stdout)
        passes = []
        for p in (self.a, self.b):
            passes.append(run(p, self.x))
            mirrored = [v[..., ::-1] for v in run(p, np.ascontiguousarray(self.x[..., ::-1]))]
            mirrored[4] = mirrored[4].copy()
            mirrored[4][:, 0] *= -1.0  # the camera's x points right
            passes.append(mirrored)
        # The passes differ (the models are not mirror-symmetric), so the
        # combination is tested, not one pass four times.
        self.assertGreater(np.abs(passes[0][0] - passes[1][0]).max(), 1e-2)
        got = run(out, self.x)
        depth = np.exp(np.mean([np.log(p[0]) for p in passes], 0))
        np.testing.assert_allclose(got[0], depth, rtol=1e-5)
        for c in (1, 2, 3):
            np.testing.assert_allclose(got[c], np.mean([p[c] for p in passes], 0), atol=1e-6)
        n = np.mean([p[4] for p in passes], 0)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        np.testing.assert_allclose(got[4], n, atol=1e-5)
        np.testing.assert_allclose(np.linalg.norm(got[4], axis=1), 1.0, atol=1e-5)

    def test_weights_are_stored_once_and_metadata_kept(self):
        out = os.path.join(self.tmp.name, "ens.onnx")
        self.assertEqual(ensemble(self.a, "--flip", "--out", out).returncode, 0)
        m = onnx.load(out)
        self.assertEqual(sum(t.name.endswith("/w") for t in m.graph.initializer), 1)
        meta = {p.key: p.value for p in m.metadata_props}
        self.assertEqual(meta["matflow.depth"], "z")
        self.assertIn("2 passes", meta["matflow.ensemble"])
        self.assertIn("mirrored", meta["matflow.ensemble"])

    def test_models_off_the_contract_are_refused_by_name(self):
        bad = os.path.join(self.tmp.name, "disparity.onnx")
        small_model(bad, 4, depth_meta="disparity")
        r = ensemble(self.a, bad, "--out", os.path.join(self.tmp.name, "x.onnx"))
        self.assertNotEqual(r.returncode, 0)
        self.assertIn("disparity.onnx", r.stderr)
        self.assertIn("matflow.depth", r.stderr)
        renamed = os.path.join(self.tmp.name, "renamed.onnx")
        small_model(renamed, 5, names=("z", "albedo", "roughness", "metallic", "normal"))
        r = ensemble(renamed, "--out", os.path.join(self.tmp.name, "y.onnx"))
        self.assertNotEqual(r.returncode, 0)
        self.assertIn("renamed.onnx: outputs", r.stderr)
        self.assertFalse(os.path.exists(os.path.join(self.tmp.name, "y.onnx")))


if __name__ == "__main__":
    unittest.main()
