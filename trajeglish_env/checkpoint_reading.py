"""Reading extensions: a trained model that reads a finer vocabulary than it draws.

A model trained on the shipped 384 templates cannot track a motion outside them: a 40 m/s ego or a reversing
car falls metres behind its tokenized track, so the NPCs see it where it is not. Extending the vocabulary
(:func:`~trajeglish_env.tokenizer.extend.extend_vocabulary`) fixes the tracking, but a model that *draws* from
2,048 tokens it was never trained on splits each old token's probability over its copies, which makes parallel
decoding's drafts miss three times as often (a third of the speed) and lets the copies far from their old
template (up to 40 m/s for the top-speed one) be drawn as often as the template itself.

A reading extension keeps what the model draws exactly as it was and extends only what it reads: every token
of the finer vocabulary is read with the embedding of the old template it was copied from (the nearest, as a
training extension starts), and the model draws its old tokens with their old logits
(``ModelConfig.drawn_size``). Agents the model does not drive are then tracked within 5 cm; the NPCs it drives
move as before.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math

import torch

from trajeglish_env.checkpoint import Checkpoint, CheckpointError
from trajeglish_env.model.network import TrajeglishModel
from trajeglish_env.tokenizer.extend import embedding_sources
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary

_EXTENSION_KEYS = ("extends", "coverage", "nominal_vocab_size")


def is_reading(ckpt: Checkpoint) -> bool:
    """Whether the checkpoint reads more tokens than it draws."""
    return ckpt.config.drawn < ckpt.config.vocab_size


def reading_extension(ckpt: Checkpoint, vocabulary: MotionVocabulary) -> Checkpoint:
    """``ckpt`` reading ``vocabulary`` (which extends its own: ``tokenizer extend``) and drawing only its
    own tokens, with the same logits; a :class:`CheckpointError` when it reads an extension already or
    ``vocabulary`` does not extend its vocabulary."""
    where = f"reading extension of {ckpt.path or 'the checkpoint'}"
    if is_reading(ckpt):
        raise CheckpointError(
            f"{where}: it reads an extended vocabulary already ({ckpt.config.vocab_size} tokens, draws "
            f"{ckpt.config.drawn}); extend the model it was made from"
        )
    try:
        sources = torch.from_numpy(embedding_sources(ckpt.vocabulary, vocabulary))  # [K, V']
    except ValueError as exc:
        raise CheckpointError(f"{where}: {exc}") from exc
    cfg = dataclasses.replace(ckpt.config, vocab_size=vocabulary.size, drawn_size=ckpt.config.vocab_size)
    state = ckpt.model.state_dict()
    k, kinds = cfg.num_kinds, torch.arange(cfg.num_kinds)[:, None]
    old = state["token.weight"].view(k, ckpt.config.vocab_size, -1)
    state["token.weight"] = old[kinds, sources].reshape(k * vocabulary.size, -1)
    if "token_bias" in state:  # only the drawn tokens' biases are used; the others keep their source's
        state["token_bias"] = state["token_bias"].view(k, -1)[kinds, sources].reshape(-1)
    state["token_source"] = sources
    model = TrajeglishModel(cfg)
    model.load_state_dict(state)
    training = {
        **ckpt.training,
        "reading_extension": {
            "from": ckpt.path.name if ckpt.path else "",
            "from_sha256": hashlib.sha256(ckpt.path.read_bytes()).hexdigest() if ckpt.path else "",
            "drawn_tokens": ckpt.config.vocab_size,
            "read_tokens": vocabulary.size,
        },
    }
    return Checkpoint(model=model.eval(), vocabulary=vocabulary, training=training)


def drawn_base(ckpt: Checkpoint) -> Checkpoint:
    """The model a reading extension was made from (its drawn tokens, their weights and templates); any
    other checkpoint as it is. Training starts from this: every token a model trains on, it draws."""
    if not is_reading(ckpt):
        return ckpt
    d, v, k = ckpt.config.drawn, ckpt.config.vocab_size, ckpt.config.num_kinds
    state = ckpt.model.state_dict()
    state.pop("token_source")
    state["token.weight"] = state["token.weight"].view(k, v, -1)[:, :d].reshape(k * d, -1)
    if "token_bias" in state:
        state["token_bias"] = state["token_bias"].view(k, v)[:, :d].reshape(-1)
    model = TrajeglishModel(dataclasses.replace(ckpt.config, vocab_size=d, drawn_size=0))
    model.load_state_dict(state)
    meta = {key: value for key, value in ckpt.vocabulary.metadata.items() if key not in _EXTENSION_KEYS}
    base_coverage = ckpt.vocabulary.metadata.get("extends", {}).get("base_coverage")
    if base_coverage is not None:
        meta["coverage"] = base_coverage
    vocabulary = MotionVocabulary(
        ckpt.vocabulary.templates[:, :d].copy(),
        method=ckpt.vocabulary.metadata.get("extends", {}).get("base_method", ckpt.vocabulary.method),
        metadata=meta,
    )
    training = {key: value for key, value in ckpt.training.items() if key != "reading_extension"}
    return dataclasses.replace(ckpt, model=model.eval(), vocabulary=vocabulary, training=training)


def training_start(
    ckpt: Checkpoint | None, vocabulary: MotionVocabulary | None
) -> tuple[Checkpoint | None, MotionVocabulary | None]:
    """What a run started from ``ckpt`` trains: a reading extension's base, on the vocabulary it reads
    unless ``vocabulary`` is given (its every token then drawn, the copies sharing their source's
    probability: ``checkpoint.load_into``); any other checkpoint as it is."""
    if ckpt is None or not is_reading(ckpt):
        return ckpt, vocabulary
    return drawn_base(ckpt), vocabulary or ckpt.vocabulary


def fine_tune_note(name: str, ckpt: Checkpoint) -> str:
    """What a fine-tune of reading extension ``ckpt`` (``--init name``) trains, and how to keep its form."""
    v, d = ckpt.config.vocab_size, ckpt.config.drawn
    return (
        f"train: --init {name} reads {v} tokens and draws {d}: this run learns to draw all {v} (its NLL "
        f"counts {v}-way targets, about {math.log(v / d):.2f} nats above the same quality over {d}); to "
        f"train the drawn model alone pass --vocab with its {d}-token vocabulary (the shipped one: "
        "--vocab shipped), then extend it again (tokenizer extend --base "
        f"RUN/model.pt --size {v} --out V.npz --reading-out FILE)"
    )
