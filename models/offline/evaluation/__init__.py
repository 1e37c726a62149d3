"""Leave-one-texture-out evaluation: data assembly, estimators, metrics, the fold runner."""
