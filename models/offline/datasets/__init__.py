"""Dataset format, validation and the builders for each source (HaTT–TexNet, synthetic, recordings)."""
