"""noisefeat: sub-image -> 26 noise features (12 conv layers + 1 wavelet layer), torch on CPU."""
from .base import FEATURE_NAMES, N_FEATURES, FeatureBase
from .blocks import merge_blocks, split_blocks
from .display import display, lightness
from .extract import default_base, extract_features

__all__ = ["FeatureBase", "FEATURE_NAMES", "N_FEATURES", "split_blocks", "merge_blocks",
           "extract_features", "default_base", "display", "lightness"]
