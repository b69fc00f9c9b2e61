"""The ESCAPE network, its loss, training and ONNX export (the only part that imports torch)."""
