"""Tactile signals and features: resampling, filtering, DFT321, windowing, MFCC/DWT/DFT features.

numpy/scipy/librosa only; serving imports this package, training calls the same functions.
"""

from models.tactile.config import TactileConfig
from models.tactile.dft321 import dft321
from models.tactile.features import recording_features, window_features
from models.tactile.preprocess import TactilePreprocessor, TactileWindow, WindowBatch
from models.tactile.resample import Resampler, resample

__all__ = [
    "Resampler",
    "TactileConfig",
    "TactilePreprocessor",
    "TactileWindow",
    "WindowBatch",
    "dft321",
    "recording_features",
    "resample",
    "window_features",
]
