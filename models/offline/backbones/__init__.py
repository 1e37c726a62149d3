"""Torch visual backbones (ResNet-50, EfficientNet-Lite0) and their ONNX export; training side only."""
