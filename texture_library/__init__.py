"""Texture library: perceptual ratings, vibration (rendering) models, the synthetic world.

Imports nothing else of hapticlink; drivers, models and the service build on it.
"""
