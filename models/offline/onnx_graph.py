"""Build ONNX graphs for the non-torch estimators with onnx.helper: ridge, the additive-kernel models
(kernel ridge, kernel SVR), their mean and the nested-CV selection of them. The older SVR, k-NN
and stack have no export and are timed in Python.

An exportable estimator has `add_graph(g) -> str`: it adds its nodes to a `GraphBuilder` and
returns the name of its (N, 4) bipolar output. Composite models call their members' add_graph on
the same builder, so one graph holds them all and shares the inputs. `export_graph` (or `save`)
clips to the rating range and writes the file with its metadata. The graph takes raw features:
standardisation and block weights are part of it, as for the nets.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.inference.modelfile import OUTPUT
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
        self.initializers.append(
            numpy_helper.from_array(arr.astype(np.int64 if arr.dtype.kind in "iu" else np.float32), name)
        )
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
    def standardized(
        self, name: str, mean: np.ndarray, std: np.ndarray, weight: float = 1.0, clip: float | None = None
    ) -> str:
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

    def squared_distances(self, z: str, centres: np.ndarray) -> str:
        """(N, m) squared Euclidean distances of the rows of z (N, D) to fixed centres (m, D), ≥ 0.

        ‖z‖² − 2 z·c + ‖c‖², the expansion numpy uses too; clamped at 0 against rounding."""
        centres = np.asarray(centres, np.float64)
        zz = self.op("ReduceSumSquare", z, axes=[1], keepdims=1)
        cross = self.op("MatMul", z, self.const(-2.0 * centres.T, "centres_t"))
        d2 = self.op("Add", self.op("Add", zz, cross), self.const(np.sum(centres**2, axis=1)[None, :], "centres_sq"))
        return self.op("Max", d2, self.const(np.array(0.0)))

    def mean_of(self, outputs: list[str]) -> str:
        """Element-wise mean of equally shaped outputs."""
        if len(outputs) == 1:
            return outputs[0]
        return self.op("Mul", self.op("Sum", *outputs), self.const(np.array(1.0 / len(outputs))))

    def pick_columns(self, outputs: list[str], owner: list[int]) -> str:
        """(N, 4) whose column j is column j of outputs[owner[j]]: per-attribute models in one output."""
        if len(set(owner)) == 1:
            return outputs[owner[0]]
        parts = []
        for k, out in enumerate(outputs):
            mask = np.array([[1.0 if o == k else 0.0 for o in owner]])
            if mask.any():
                parts.append(self.op("Mul", out, self.const(mask, "column_mask")))
        return parts[0] if len(parts) == 1 else self.op("Sum", *parts)

    def save(self, path: str | Path, output: str, metadata: dict[str, str]) -> Path:
        import onnx
        from onnx import TensorProto, helper

        clipped = self.op(
            "Clip", output, self.const(np.array(RATING_MIN)), self.const(np.array(RATING_MAX)), hint=OUTPUT
        )
        self.nodes.append(helper.make_node("Identity", [clipped], [OUTPUT]))
        graph = helper.make_graph(
            self.nodes,
            "hapticlink",
            [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["batch", w]) for n, w in self.inputs.items()],
            [helper.make_tensor_value_info(OUTPUT, TensorProto.FLOAT, ["batch", 4])],
            self.initializers,
        )
        model = helper.make_model(
            graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="hapticlink", ir_version=IR_VERSION
        )
        for k, v in metadata.items():
            entry = model.metadata_props.add()
            entry.key, entry.value = k, v
        onnx.checker.check_model(model)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        onnx.save(model, str(path))
        return path


def export_graph(estimator, path: str | Path, metadata: dict[str, str]) -> Path:
    """Write a fitted estimator that has `add_graph` as one ONNX file (inputs tactile and/or visual, output ratings)."""
    g = GraphBuilder()
    return g.save(path, estimator.add_graph(g), metadata)
