"""Figures and the markdown report of evaluation results."""
