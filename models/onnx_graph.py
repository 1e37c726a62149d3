"""Build ONNX graphs for the non-torch estimators with onnx.helper (today: ridge; SVR, k-NN and
the stack have no export and are timed in Python).

An estimator adds its nodes to a `GraphBuilder` and passes the name of its (N, 4) bipolar output
to `save`; `save` clips to the rating range and writes the file with its metadata. The
graph takes raw features: standardisation and block weights are part of it, as for the nets.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.modelfile import OUTPUT
from texture_library.attributes import RATING_MAX, RATING_MIN

OPSET = 17
IR_VERSION = 9  # onnxruntime 1.17+ reads it; newer onnx packages default to a newer IR than older runtimes load


class GraphBuilder:
    """Accumulates nodes, constants and the graph inputs (tactile and/or visual)."""

    def __init__(self) -> None:
        self.nodes: list = []
        self.initializers: list = []
        self.inputs: dict[str, int] = {}
        self._count = 0

    def input(self, name: str, width: int) -> str:
        if name in self.inputs and self.inputs[name] != width:
            raise ValueError(f"graph input {name!r} declared with widths {self.inputs[name]} and {width}")
        self.inputs[name] = width
        return name

    def const(self, array: np.ndarray, hint: str = "c") -> str:
        from onnx import numpy_helper

        name = self._name(hint)
        arr = np.asarray(array)
        self.initializers.append(numpy_helper.from_array(arr.astype(np.int64 if arr.dtype.kind in "iu" else np.float32), name))
        return name

    def op(self, op_type: str, *inputs: str, hint: str | None = None, outputs: int = 1, **attrs) -> str | list[str]:
        from onnx import helper

        names = [self._name(hint or op_type.lower()) for _ in range(outputs)]
        self.nodes.append(helper.make_node(op_type, list(inputs), names, **attrs))
        return names[0] if outputs == 1 else names

    def _name(self, hint: str) -> str:
        self._count += 1
        return f"{hint}_{self._count}"

    # ---- shared pieces ------------------------------------------------------------------------
    def standardized(self, name: str, mean: np.ndarray, std: np.ndarray, weight: float = 1.0, clip: float | None = None) -> str:
        """weight · z for graph input `name`, z = (x − mean) / std, clipped to ±clip when given."""
        x = self.input(name, int(np.size(mean)))
        centred = self.op("Sub", x, self.const(mean, f"{name}_mean"))
        z = self.op("Mul", centred, self.const(weight / np.asarray(std, float), f"{name}_scale"))
        if clip is None:
            return z
        bound = clip * weight
        return self.op("Clip", z, self.const(np.array(-bound)), self.const(np.array(bound)))

    def concat(self, parts: list[str]) -> str:
        return parts[0] if len(parts) == 1 else self.op("Concat", *parts, axis=1)

    def save(self, path: str | Path, output: str, metadata: dict[str, str]) -> Path:
        import onnx
        from onnx import TensorProto, helper

        clipped = self.op("Clip", output, self.const(np.array(RATING_MIN)), self.const(np.array(RATING_MAX)), hint=OUTPUT)
        self.nodes.append(helper.make_node("Identity", [clipped], [OUTPUT]))
        graph = helper.make_graph(
            self.nodes, "hapticlink",
            [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["batch", w]) for n, w in self.inputs.items()],
            [helper.make_tensor_value_info(OUTPUT, TensorProto.FLOAT, ["batch", 4])],
            self.initializers,
        )
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="hapticlink",
                                  ir_version=IR_VERSION)
        for k, v in metadata.items():
            entry = model.metadata_props.add()
            entry.key, entry.value = k, v
        onnx.checker.check_model(model)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        onnx.save(model, str(path))
        return path
