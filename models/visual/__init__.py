"""Visual features of texture images: grid patches → CNN backbone (averaged) ⊕ 16-level GLCM.

Torch-free modules (safe for the service): config, image, patches, glcm,
augment, cache, embedding, onnx_backbone (its export function imports torch
lazily). Torch modules (training/export only): resnet, efficientnet, backbone.
This package imports none of them eagerly, so `import models.visual` stays light.
"""
