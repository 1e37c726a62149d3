"""Networks (torch): Visuo-tactile Net and its branches, baselines, training, ONNX export.

Nothing is imported here on purpose: `export` and `latency` import torch only inside their
functions, so code that imports them (or this package) does not pull torch in until it needs it.

- `convlstm`   ConvLSTM1D with Keras semantics
- `hvnet`      HV-Net, the visual 1-D conv autoencoder
- `htnet`      HT-Net, the tactile ConvLSTM stack
- `fusion`     VisuoTactileNet (both / tactile / visual), MLPBranch, FusionHead
- `baselines`  ANN, Vision1DCNN, HapticCNN, TactileCNNLSTM
- `presets`    named presets: build(name, visual_dim, tactile_dim), NAMES
- `training`   TrainConfig, TrainArrays, train_net, predict_windows
- `export`     export_onnx (raw features in, bipolar ratings out)
- `latency`    onnx_latency, param_count
"""
