"""Export a linear model on standardised feature blocks as ONNX (raw features in, bipolar ratings out).

    ratings = clip( concat_b((x_b − mean_b) / std_b · w_b) @ coef + intercept, −100, 100 )

Built directly with onnx.helper: a ridge regression needs no torch to serve.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.modelfile import OUTPUT
from texture_library.attributes import RATING_MAX, RATING_MIN

OPSET = 17
IR_VERSION = 9  # onnx 1.15 level; opset 17 needs IR ≥ 8, onnxruntime ≥ 1.16 loads it


@dataclass(frozen=True)
class InputBlock:
    """One graph input: name ("tactile" | "visual"), its standardisation and block weight."""

    name: str
    mean: np.ndarray
    std: np.ndarray
    weight: float


def export_linear(path: str | Path, blocks: list[InputBlock], coef: np.ndarray, intercept: np.ndarray, metadata: dict[str, str]) -> Path:
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    coef = np.asarray(coef, np.float32)
    width = sum(b.mean.size for b in blocks)
    if coef.shape != (width, 4):
        raise ValueError(f"coef must be ({width}, 4) for blocks of total width {width}, got {coef.shape}")
    nodes, inits, inputs, parts = [], [], [], []
    for b in blocks:
        inputs.append(helper.make_tensor_value_info(b.name, TensorProto.FLOAT, ["batch", int(b.mean.size)]))
        inits += [
            numpy_helper.from_array(np.asarray(b.mean, np.float32), f"{b.name}_mean"),
            numpy_helper.from_array((np.float32(b.weight) / np.asarray(b.std, np.float32)), f"{b.name}_scale"),
        ]
        nodes += [
            helper.make_node("Sub", [b.name, f"{b.name}_mean"], [f"{b.name}_centred"]),
            helper.make_node("Mul", [f"{b.name}_centred", f"{b.name}_scale"], [f"{b.name}_z"]),
        ]
        parts.append(f"{b.name}_z")
    inits += [
        numpy_helper.from_array(coef, "coef"),
        numpy_helper.from_array(np.asarray(intercept, np.float32), "intercept"),
        numpy_helper.from_array(np.array(RATING_MIN, np.float32), "lo"),
        numpy_helper.from_array(np.array(RATING_MAX, np.float32), "hi"),
    ]
    if len(parts) > 1:
        nodes.append(helper.make_node("Concat", parts, ["z"], axis=1))
    else:
        nodes.append(helper.make_node("Identity", parts, ["z"]))
    nodes += [
        helper.make_node("MatMul", ["z", "coef"], ["linear"]),
        helper.make_node("Add", ["linear", "intercept"], ["unclipped"]),
        helper.make_node("Clip", ["unclipped", "lo", "hi"], [OUTPUT]),
    ]
    graph = helper.make_graph(nodes, "hapticlink_linear", inputs,
                              [helper.make_tensor_value_info(OUTPUT, TensorProto.FLOAT, ["batch", 4])], inits)
    # IR version pinned: onnx's newest IR can be ahead of what the installed onnxruntime loads
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="hapticlink", ir_version=IR_VERSION)
    for k, v in metadata.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    onnx.checker.check_model(model)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path
