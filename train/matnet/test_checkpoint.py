#!/usr/bin/env python3
"""Tests of checkpoint.py (plain Python; `tests/export_tool.rs` runs it
in `cargo test`): the official layout, and how the usual checkpoints map
onto it.

  python3 train/matnet/test_checkpoint.py"""
import math
import os
import sys
import unittest

sys.dont_write_bytecode = True
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import checkpoint as ck  # noqa: E402

# The LPIPS (AlexNet) loss network's keys in the official trainer's
# checkpoint (torchmetrics 1.4.0), with their shapes.
ALEX = [(64, 3, 11), (192, 64, 5), (384, 192, 3), (256, 384, 3), (256, 256, 3)]
LPIPS = {}
for i, (o, c, k) in zip([0, 3, 6, 8, 10], ALEX):
    s = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}[i]
    LPIPS[f"criterion_lpips.net.net.slice{s}.{i}.weight"] = (o, c, k, k)
    LPIPS[f"criterion_lpips.net.net.slice{s}.{i}.bias"] = (o,)
for j, (o, _, _) in enumerate(ALEX):
    LPIPS[f"criterion_lpips.net.lin{j}.model.1.weight"] = (1, o, 1, 1)
    LPIPS[f"criterion_lpips.net.lins.{j}.model.1.weight"] = (1, o, 1, 1)


def released():
    return dict(ck.official_layout())


def lightning():
    out = {ck.LIGHTNING_PREFIX + k: v for k, v in ck.official_layout()}
    out.update(LPIPS)
    return out


def check(shapes, renames=(), drops=()):
    names, errors = ck.map_names(list(shapes), renames, drops)
    mapped = {new: shapes[old] for new, old in names.items()}
    return errors + ck.compare(ck.official_layout(), mapped)


class Layout(unittest.TestCase):
    def test_the_official_counts(self):
        lay = ck.official_layout()
        self.assertEqual(len(lay), 303)
        self.assertEqual(len({n for n, _ in lay}), 303)
        self.assertEqual(sum(math.prod(s) for _, s in lay), 108_361_321)
        self.assertEqual(sum(n.startswith("pretrained.") for n, _ in lay), 175)
        self.assertEqual(sum(n.startswith("depth_head.") for n, _ in lay), 64)
        self.assertEqual(sum(n.startswith("material_head.") for n, _ in lay), 64)

    def test_official_order_inside_a_fusion_block(self):
        names = [n for n, _ in ck.official_layout() if n.startswith("depth_head.scratch.refinenet1.")]
        self.assertTrue(names[0].endswith("out_conv.weight"))
        self.assertTrue(names[2].startswith("depth_head.scratch.refinenet1.resConfUnit1."))

    def test_heads_differ_only_in_their_last_convolution(self):
        lay = dict(ck.official_layout())
        self.assertEqual(lay["depth_head.scratch.output_conv2.2.weight"], (1, 32, 1, 1))
        self.assertEqual(lay["material_head.scratch.output_conv2.2.weight"], (8, 32, 1, 1))
        self.assertEqual(lay["pretrained.pos_embed"], (1, 1370, 768))


class Mapping(unittest.TestCase):
    def test_the_released_state_dict_loads_as_it_is(self):
        self.assertEqual(check(released()), [])

    def test_a_training_checkpoint_needs_a_rename_and_a_drop_and_says_so(self):
        self.assertEqual(len(LPIPS), 20)
        problems = check(lightning())
        self.assertEqual(sum(p.startswith("missing:") for p in problems), 303)
        self.assertEqual(problems[-1], "try: --drop criterion_lpips. --rename matnet.=")
        self.assertEqual(check(lightning(), [("matnet.", "")], ["criterion_lpips."]), [])

    def test_a_rename_alone_leaves_the_loss_keys_named(self):
        problems = check(lightning(), [("matnet.", "")])
        self.assertEqual(len(problems), 21)
        self.assertIn("unexpected: criterion_lpips.net.lins.4.model.1.weight [1, 256, 1, 1]", problems)
        self.assertEqual(problems[-1], "try: --drop criterion_lpips.")

    def test_a_missing_and_a_misshaped_key_are_named(self):
        s = released()
        del s["pretrained.norm.bias"]
        s["material_head.scratch.output_conv2.2.weight"] = (5, 32, 1, 1)
        self.assertEqual(
            check(s),
            [
                "missing:    pretrained.norm.bias [768]",
                "shape:      material_head.scratch.output_conv2.2.weight is [5, 32, 1, 1], "
                "the architecture has [8, 32, 1, 1]",
            ],
        )

    def test_a_flag_that_matches_nothing_is_an_error(self):
        problems = check(released(), [("matnet.", "")], ["criterion_lpips."])
        self.assertIn("--drop criterion_lpips.: no key starts with 'criterion_lpips.'", problems)
        self.assertIn("--rename matnet.=: no key (left after the drops) starts with 'matnet.'", problems)

    def test_two_names_mapped_to_one_is_an_error(self):
        s = {"module." + k: v for k, v in ck.official_layout()}
        s["pretrained.norm.bias"] = (768,)
        names, errors = ck.map_names(list(s), [("module.", "")])
        self.assertEqual(errors, ["'module.pretrained.norm.bias' and 'pretrained.norm.bias' both become 'pretrained.norm.bias'"])

    def test_a_data_parallel_prefix_is_suggested(self):
        s = {"module." + k: v for k, v in ck.official_layout()}
        self.assertEqual(check(s)[-1], "try: --rename module.=")

    def test_rename_syntax(self):
        self.assertEqual(ck.parse_rename("matnet.="), ("matnet.", ""))
        self.assertEqual(ck.parse_rename("a.=b."), ("a.", "b."))
        with self.assertRaises(ValueError):
            ck.parse_rename("matnet.")
        with self.assertRaises(ValueError):
            ck.parse_rename("=x")


if __name__ == "__main__":
    unittest.main(verbosity=1)
