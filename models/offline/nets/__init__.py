"""Networks (torch): Visuo-tactile Net and its branches, baselines, training, ONNX export.

Nothing is imported here on purpose: the serving path imports `models.offline.nets.export`
(`models.inference.modelfile`) and `models.offline.nets.latency`, which must not pull in torch.

- `convlstm`   ConvLSTM1D with Keras semantics
- `hvnet`      HV-Net, the visual 1-D conv autoencoder
- `htnet`      HT-Net, the tactile ConvLSTM stack
- `fusion`     VisuoTactileNet (both / tactile / visual), MLPBranch, FusionHead
- `baselines`  ANN, Vision1DCNN, HapticCNN, TactileCNNLSTM
- `registry`   named presets: build(name, visual_dim, tactile_dim), NAMES
- `training`   TrainConfig, TrainArrays, train_net, predict_windows
- `export`     export_onnx (raw features in, bipolar ratings out)
- `latency`    onnx_latency, param_count
"""
