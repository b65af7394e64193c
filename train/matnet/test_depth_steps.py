#!/usr/bin/env python3
"""Tests of depth_steps.py's measure (numpy only; `tests/predict.rs`
runs it in `cargo test`): on depth maps with known steps, the shares it
reports are the ones counted by hand.

  python3 train/matnet/test_depth_steps.py"""
import os
import sys
import unittest

import numpy as np

sys.dont_write_bytecode = True
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from depth_steps import dilate, measure, steps  # noqa: E402

N = 20


def wall_and_box(box_x=10):
    """A wall at 4 m with a box at 2 m over the columns from box_x on."""
    z = np.full((N, N), 4.0, np.float32)
    z[:, box_x:] = 2.0
    return z


class DepthSteps(unittest.TestCase):
    def test_a_step_is_marked_on_the_near_side_of_the_jump(self):
        s = steps(np.log(wall_and_box()), 0.05)
        self.assertEqual(s.sum(), N)
        self.assertTrue(s[:, 9].all())
        # A smooth ramp (0.01 a pixel in log z) has none.
        ramp = np.exp(np.tile(np.arange(N) * 0.01, (N, 1)))
        self.assertEqual(steps(np.log(ramp), 0.05).sum(), 0)

    def test_the_truth_measured_against_itself_has_no_false_steps(self):
        z, v = wall_and_box(), np.ones((N, N), bool)
        share, false, recall = measure(z, z, v)
        self.assertAlmostEqual(share, N / N**2)
        self.assertEqual(false, 0.0)
        self.assertEqual(recall, 1.0)

    def test_a_step_where_the_truth_has_none_is_false(self):
        true, v = wall_and_box(), np.ones((N, N), bool)
        pred = true.copy()
        pred[:, :4] = 3.0  # a step between columns 3 and 4: 6 px from the true one
        share, false, recall = measure(pred, true, v)
        self.assertAlmostEqual(share, 2 * N / N**2)
        self.assertAlmostEqual(false, N / N**2)
        self.assertEqual(recall, 1.0)

    def test_a_step_two_pixels_off_counts_as_found(self):
        true, v = wall_and_box(10), np.ones((N, N), bool)
        share, false, recall = measure(wall_and_box(12), true, v)
        self.assertEqual((false, recall), (0.0, 1.0))
        share, false, recall = measure(wall_and_box(13), true, v)
        self.assertAlmostEqual(false, N / N**2)
        self.assertEqual(recall, 0.0)

    def test_pixels_near_invalid_ones_are_left_out(self):
        true, v = wall_and_box(), np.ones((N, N), bool)
        v[:, 8] = False
        self.assertEqual(measure(true, true, v)[0], 0.0)
        self.assertTrue(dilate(~v, 2)[:, 6:11].all())


if __name__ == "__main__":
    unittest.main(verbosity=2)
