"""Visual features of texture images: grid patches → CNN backbone (averaged) ⊕ 16-level GLCM.

Every module here is torch-free (safe for the service): config, image, patches, glcm, descriptors,
augment, cache, pooling, embedding, onnx_backbone. The torch backbones and their ONNX export live in the
offline wing (`models.offline.backbones`: cnn, resnet, efficientnet, onnx_export, quantize).
"""
