"""The Trajeglish model: configuration, masks, layers, the scene encoder and the encoder-decoder network."""

from trajeglish_env.model.config import PRESETS, ModelConfig, Variant, preset
from trajeglish_env.model.network import SceneInputs, TrajeglishModel

__all__ = ["PRESETS", "ModelConfig", "SceneInputs", "TrajeglishModel", "Variant", "preset"]
