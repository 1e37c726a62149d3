"""Datasets, tactile and visual features, networks, training, evaluation, export, prediction."""
