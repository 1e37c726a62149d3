"""The int8 test's own copies against fp32 on its 6 held-out photos, on the CPU this runs on (an emulated one too).

    python -m benchmarks.int8_test_set build [--dir DIR]    # natively: quantize, save the photos' patches
    [qemu-x86_64 -cpu Haswell] python -m benchmarks.int8_test_set run [--dir DIR]

tests/models/offline/backbones/test_quantize.py quantizes EfficientNet-Lite0 with a small calibration (4 procedural
photos of 448², seed 0) and compares it with fp32 on 6 others (seed 1). `build` makes that copy with recipe 1
(every convolution int8) and the served recipe (the first quantize.FP32_CONVS fp32) from the fp32 file in the backbone
cache, and saves the held-out patches; `run` needs only numpy and onnxruntime, so it runs under an emulator, where
rendering and quantizing would take long. It prints the cpuid flags numpy sees, each copy's frame cosines and its
load-time check.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

DEFAULT_DIR = Path("artifacts") / "int8-test-set"
COPIES = {"recipe 1 (all int8)": ("int8_r1.onnx", 0), "served recipe": ("int8_served.onnx", None)}


def build(folder: Path) -> None:
    from models.offline.backbones.quantize import FP32_CONVS, quantize_backbone_onnx, synthetic_patches
    from models.offline.featurize import SERVED_VISUAL, backbone_onnx

    folder.mkdir(parents=True, exist_ok=True)
    fp32 = backbone_onnx(SERVED_VISUAL.model_copy(update={"backbone": "efficientnet_lite0"}))
    (folder / "fp32.onnx").write_bytes(fp32.read_bytes())
    calibration = synthetic_patches(4, 448, seed=0)
    for name, convs in COPIES.values():
        quantize_backbone_onnx(
            folder / "fp32.onnx", folder / name, calibration, fp32_convs=FP32_CONVS if convs is None else convs
        )
    np.save(folder / "held_out.npy", synthetic_patches(6, 448, seed=1))


def run(folder: Path) -> dict:
    from benchmarks.backbone_int8 import host_isa
    from models.visual.onnx_backbone import OnnxBackbone, frame_cosines

    patches = np.load(folder / "held_out.npy")
    fp32 = OnnxBackbone(folder / "fp32.onnx", intra_op_threads=1, min_probe_cosine=None)
    reference = fp32.embed(patches).reshape(6, 4, -1).mean(1)
    host = host_isa()
    print(f"{host['isa_class']}: cpuid {host['cpuid']}")
    out = {}
    for label, (name, _) in COPIES.items():
        copy = OnnxBackbone(folder / name, intra_op_threads=1)
        cosines = frame_cosines(reference, copy.embed(patches).reshape(6, 4, -1).mean(1))
        out[label] = cosines.tolist()
        check = copy.check.describe() if copy.check is not None else "no probe"
        print(f"  {label:20s} frame cosines {np.round(cosines, 3)}; {check}")
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.int8_test_set", description=__doc__.split("\n")[0])
    parser.add_argument("step", choices=("build", "run"))
    parser.add_argument("--dir", type=Path, default=DEFAULT_DIR)
    args = parser.parse_args(argv)
    build(args.dir) if args.step == "build" else run(args.dir)


if __name__ == "__main__":
    main()
