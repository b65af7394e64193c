#!/usr/bin/env python3
"""Tests of train.py's network options that need PyTorch (not installed in
CI: run them where train.py runs, `python3 train/matnet/test_train.py`).

- `--depth-range`: a network with the depth range's layer, given a plain
  network's weights, gives the plain network's outputs (the layer starts
  at zero), and its gain and offset act on log z as documented;
- it exports to ONNX, and onnxruntime agrees with PyTorch;
- `--false-step-weight`: the false-step term's known answers.
"""

import io
import math
import os
import sys
import unittest

import numpy as np

sys.dont_write_bytecode = True
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import torch  # noqa: E402

import train  # noqa: E402


class DepthRange(unittest.TestCase):
    def setUp(self):
        torch.manual_seed(0)
        torch.set_num_threads(1)
        self.plain = train.UNet(4, False, "blend", False).eval()
        self.ranged = train.UNet(4, False, "blend", True).eval()
        missing, unexpected = self.ranged.load_state_dict(self.plain.state_dict(), strict=False)
        self.assertEqual(sorted(missing), ["depth_range.bias", "depth_range.weight"])
        self.assertEqual(unexpected, [])
        self.x = torch.rand(2, 3, 64, 64)

    def test_starts_as_the_plain_network(self):
        with torch.no_grad():
            for a, b in zip(self.plain(self.x), self.ranged(self.x)):
                self.assertTrue(torch.equal(a, b))

    def test_gain_and_offset_act_on_log_depth(self):
        with torch.no_grad():
            self.ranged.depth_range.bias.copy_(torch.tensor([0.5, 0.3]))
            want = 0.3 + np.exp(0.5) * torch.log(self.plain(self.x)[0])
            got = torch.log(self.ranged(self.x)[0])
        self.assertLess(float((got - want).abs().max()), 1e-5)

    def test_gain_is_clamped(self):
        with torch.no_grad():
            self.ranged.depth_range.bias.copy_(torch.tensor([9.0, 0.0]))
            want = np.exp(1.5) * torch.log(self.plain(self.x)[0])
            got = torch.log(self.ranged(self.x)[0])
        ok = want.abs() < 5.9  # where the depth's own clamp (e^-4 .. e^6) does not cut in
        self.assertLess(float((got - want)[ok].abs().max()), 1e-4)

    def test_onnxruntime_agrees(self):
        import onnxruntime as ort

        with torch.no_grad():
            self.ranged.depth_range.weight.normal_(0.0, 0.5)
            self.ranged.depth_range.bias.copy_(torch.tensor([0.4, -0.2]))
            want = self.ranged(self.x[:1])
        self.ranged.fixed = (64, 64)
        f = io.BytesIO()
        torch.onnx.export(self.ranged, torch.zeros(1, 3, 64, 64), f, opset_version=17, input_names=["image"],
                          output_names=train.NAMES, dynamo=False)
        s = ort.InferenceSession(f.getvalue(), providers=["CPUExecutionProvider"])
        got = s.run(None, {"image": self.x[:1].numpy()})
        for g, w in zip(got, want):
            self.assertLess(float(np.abs(g - w.numpy()).max()), 1e-4)


class FalseSteps(unittest.TestCase):
    """`--false-step-weight`: the predicted depth's steps where the true
    depth is smooth, by known answers on a 16 x 16 scene: a wall at z = 2
    with a box at z = 1 in columns 8.. (its silhouette: one column of
    steps by ln 2, 16 pixels)."""

    def setUp(self):
        z = torch.full((1, 1, 16, 16), 2.0)
        z[..., 8:] = 1.0
        self.y = {"depth": z, "valid": torch.ones(1, 1, 16, 16)}

    def test_the_truth_costs_nothing(self):
        self.assertEqual(float(train.false_step_loss(self.y["depth"] * 3.0, self.y)), 0.0)

    def test_a_step_the_truth_lacks(self):
        # A step by ln 1.5 between rows 3 and 4, all across: the columns
        # more than 2 px from the silhouette's (between 7 and 8) count,
        # 0..4 and 10..15, each beyond the hinge by ln 1.5 - 0.05, per
        # the 16 silhouette pixels.
        d = self.y["depth"].clone()
        d[..., :4, :] *= 1.5
        want = 11 * (math.log(1.5) - train.FALSE_STEP) / 16
        self.assertAlmostEqual(float(train.false_step_loss(d, self.y)), want, places=5)

    def test_steps_near_a_true_one_and_small_ones_are_free(self):
        d = self.y["depth"].clone()
        d[..., :, 6:] = 1.0  # the silhouette drawn 2 px early
        d[..., :8, :] *= 1.04  # a step below the hinge
        self.assertEqual(float(train.false_step_loss(d, self.y)), 0.0)


if __name__ == "__main__":
    unittest.main()
