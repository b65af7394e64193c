#!/usr/bin/env python3
"""Writes tests/data/identity_3x8x8.onnx: a one-node graph (Identity on an
f32 [N, 3, 8, 8] tensor), a well-formed model of the wrong shape for the
refraction-length tests. Needs the `onnx` package."""
import os
import onnx
from onnx import TensorProto, helper

x = helper.make_tensor_value_info("input", TensorProto.FLOAT, ["N", 3, 8, 8])
y = helper.make_tensor_value_info("output", TensorProto.FLOAT, ["N", 3, 8, 8])
g = helper.make_graph([helper.make_node("Identity", ["input"], ["output"])], "identity", [x], [y])
m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
m.ir_version = 8
onnx.checker.check_model(m)
here = os.path.dirname(os.path.abspath(__file__))
onnx.save(m, os.path.join(here, "..", "..", "tests", "data", "identity_3x8x8.onnx"))
