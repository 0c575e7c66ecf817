"""``train --history-dropout P``: a share of each training window's agents has its input tokens hidden, so
their next tokens must be learned from the current states a ``neighbour_input`` model reads; nothing else
of the window changes."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import small_scenes

from trajeglish_env.checkpoint import load_pretrained
from trajeglish_env.model.config import preset
from trajeglish_env.training.train import TrainConfig, train, window_config
from trajeglish_env.training.training_data import TokenizedWindows, drop_histories


@pytest.fixture(scope="module")
def windows() -> tuple[TokenizedWindows, TokenizedWindows]:
    ckpt = load_pretrained()
    scenes, window = small_scenes(), window_config(ckpt.config)
    plain = TokenizedWindows(scenes, window, ckpt.vocabulary, None, seed=5)
    dropped = TokenizedWindows(scenes, window, ckpt.vocabulary, None, seed=5, history_dropout=0.3)
    return plain, dropped


def test_only_the_dropped_agents_inputs_change(windows: tuple[TokenizedWindows, TokenizedWindows]) -> None:
    plain, dropped = windows
    hidden, real = 0, 0
    for g in range(30):  # 10 epochs of the 3 scenes
        a, b = plain[g], dropped[g]
        assert set(a) == set(b)
        for key in a:
            if key != "input_tokens":
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        gone = (b["input_tokens"] == -1).all(axis=1) & (a["input_tokens"] >= 0).any(axis=1)
        kept = ~gone
        np.testing.assert_array_equal(a["input_tokens"][kept], b["input_tokens"][kept])
        assert not gone[~a["agent_mask"]].any()  # padding slots are never counted as dropped
        hidden, real = hidden + int(gone.sum()), real + int((a["input_tokens"] >= 0).any(axis=1).sum())
        np.testing.assert_array_equal(dropped[g]["input_tokens"], b["input_tokens"])  # deterministic
    assert 0.2 < hidden / real < 0.4, (hidden, real)  # 30 % of the agents with tokens


def test_drop_histories_hides_whole_rows() -> None:
    window = {
        "agent_mask": np.array([True, True, True, False]),
        "input_tokens": np.arange(16).reshape(4, 4),
    }
    drop = drop_histories(window, 0.99, np.random.default_rng(0))
    assert drop.tolist() == [True, True, True, False]
    assert (window["input_tokens"][:3] == -1).all() and window["input_tokens"][3].tolist() == [12, 13, 14, 15]
    window["input_tokens"] = np.arange(16).reshape(4, 4)
    assert not drop_histories(window, 0.0, np.random.default_rng(0)).any()


def test_settings(tmp_path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=r"history_dropout must be in \[0, 1\), got 1.0"):
        TrainConfig(history_dropout=1.0)
    ckpt = load_pretrained()
    with pytest.raises(ValueError, match=r"history_dropout must be in \[0, 1\), got -0.1"):
        TokenizedWindows(small_scenes(), window_config(ckpt.config), ckpt.vocabulary, None, 0, None, -0.1)
    with pytest.raises(ValueError, match="history_dropout needs a model that reads its agents' neighbours"):
        train(tmp_path / "none", tmp_path / "run", preset("tiny"), TrainConfig(history_dropout=0.3))
