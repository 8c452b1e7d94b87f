"""The model: encodings, networks, the appearance head, quantized storage forms, fused inference."""
