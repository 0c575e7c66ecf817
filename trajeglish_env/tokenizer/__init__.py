"""Motion tokenizer (paper, Sec. 3.1): k-disks template vocabularies per agent class, tokenize/render,
noisy tokenization for training, the paper's baselines and their evaluation."""

from trajeglish_env.tokenizer.distance import corner_distance
from trajeglish_env.tokenizer.fit import (
    METHODS,
    evaluate_directory,
    evaluate_vocabulary_file,
    fit_from_directory,
    fit_vocabulary,
)
from trajeglish_env.tokenizer.noise import NoiseConfig
from trajeglish_env.tokenizer.tokenize import (
    TokenizedTrajectories,
    TokenizeError,
    render,
    tokenize,
    tokenize_scenario,
)
from trajeglish_env.tokenizer.vocabulary import (
    MotionVocabulary,
    VocabularyError,
    default_tokenizer_path,
    load_default_tokenizer,
)

__all__ = [
    "METHODS",
    "MotionVocabulary",
    "NoiseConfig",
    "TokenizeError",
    "TokenizedTrajectories",
    "VocabularyError",
    "corner_distance",
    "default_tokenizer_path",
    "evaluate_directory",
    "evaluate_vocabulary_file",
    "fit_from_directory",
    "fit_vocabulary",
    "load_default_tokenizer",
    "render",
    "tokenize",
    "tokenize_scenario",
]
