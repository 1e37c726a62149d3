"""Inference on the serving side: the ONNX predictor, the model card, intervals, OOD flags, standardisation."""
