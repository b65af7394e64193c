#!/usr/bin/env python3
"""Two tiny ONNX models for matflow's tests of MatNet's contract
(tests/data/):

  matnet_heads_dynamic.onnx  a valid model of the two-head layout: input
      image [N, 3, H, W] with dynamic spatial axes (so matflow feeds it
      518 x 518, MatNet's size); outputs depth [N, 1, H, W] (the channel
      mean, ReLU, + 0.1: disparity-like, no metadata) and material
      [N, 8, H, W] (albedo = image, roughness = red, metallic = green,
      normals = image, renormalised by matflow).
  matnet_wrong_channels.onnx the five named outputs, but albedo has 2
      channels: matflow must refuse it, naming the output.
"""

import os

import onnx
from onnx import TensorProto, helper

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "..", "..", "tests", "data")


def const(name, values):
    return helper.make_node(
        "Constant", [], [name], value=helper.make_tensor(name + "_v", TensorProto.INT64, [len(values)], values)
    )


def slice_ch(src, dst, c0, c1, tag):
    return [
        const(f"{tag}_s", [c0]),
        const(f"{tag}_e", [c1]),
        const(f"{tag}_a", [1]),
        helper.make_node("Slice", [src, f"{tag}_s", f"{tag}_e", f"{tag}_a"], [dst]),
    ]


def heads():
    nodes = [
        helper.make_node("ReduceMean", ["image"], ["mean"], axes=[1], keepdims=1),
        helper.make_node("Relu", ["mean"], ["relu"]),
        helper.make_node(
            "Constant", [], ["tenth"], value=helper.make_tensor("tenth_v", TensorProto.FLOAT, [], [0.1])
        ),
        helper.make_node("Add", ["relu", "tenth"], ["depth"]),
    ]
    nodes += slice_ch("image", "rm", 0, 2, "rm")
    nodes.append(helper.make_node("Concat", ["image", "rm", "image"], ["material"], axis=1))
    shape = ["N", 3, "H", "W"]
    g = helper.make_graph(
        nodes,
        "matnet_heads_dynamic",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, shape)],
        [
            helper.make_tensor_value_info("depth", TensorProto.FLOAT, ["N", 1, "H", "W"]),
            helper.make_tensor_value_info("material", TensorProto.FLOAT, ["N", 8, "H", "W"]),
        ],
    )
    return helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)], producer_name="matflow-tests")


def wrong_channels():
    nodes = []
    nodes += slice_ch("image", "depth", 0, 1, "d")
    nodes += slice_ch("image", "albedo", 0, 2, "a")
    nodes += slice_ch("image", "roughness", 1, 2, "r")
    nodes += slice_ch("image", "metallic", 2, 3, "m")
    nodes.append(helper.make_node("Identity", ["image"], ["normal"]))
    outs = [("depth", 1), ("albedo", 2), ("roughness", 1), ("metallic", 1), ("normal", 3)]
    g = helper.make_graph(
        nodes,
        "matnet_wrong_channels",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 32, 32])],
        [helper.make_tensor_value_info(n, TensorProto.FLOAT, [1, c, 32, 32]) for n, c in outs],
    )
    return helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)], producer_name="matflow-tests")


for name, m in [("matnet_heads_dynamic.onnx", heads()), ("matnet_wrong_channels.onnx", wrong_channels())]:
    m.ir_version = 8
    onnx.checker.check_model(m)
    onnx.save(m, os.path.join(OUT, name))
    print("wrote", name)
